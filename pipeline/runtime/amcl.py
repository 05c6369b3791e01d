"""Adaptive Monte Carlo localization on a laser map (seed 000 section 3.2 and Algorithm 1; Thrun et al. ch. 8).

One filter, four methods (`FilterConfig.method`), so the paper's comparisons run in the same code:

- `amcl`: augmented MCL (random free-space particles with probability max(0, 1 - w_fast / w_slow))
  plus KLD-sampling: what the robot runs.
- `kld`: KLD-sampling only. `mcl`: a fixed count (max_particles), no injection.
The particle budget is max_particles, or max_particles_per_ha of the map's free space where more.
- `mixture`: mixture MCL (Thrun, Fox, Burgard, Dellaert 2001): a share of each new set is drawn from
  the dual proposal (free-space poses drawn in proportion to the scan's likelihood) and weighted by the
  prior belief's density there (a kernel density estimate of the moved particles).

Updates are gated by travel (update_min_d, update_min_a) as in nav2: between updates odometry only
accumulates. States: `tracking`, `lost` (the kidnap rule fired), `relocalising` (after a global start or
an injection, until one cluster holds the weight and is tight). The kidnap rule is the paper's (the best
particle's likelihood below a threshold) made robust: the per-beam relative likelihood, several updates
in a row, or w_fast / w_slow collapsing. `inject` is the hook the camera path calls while not tracking.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from pipeline.io.odometry import noise_alphas
from pipeline.runtime import inputs
from pipeline.runtime.estimate import PoseEstimate, estimate_pose, mode_near_best
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.motion import (
    compose2d,
    inverse2d,
    odometry_delta,
    sample_motion_model_odometry,
    wrap_angle,
)
from pipeline.runtime.sampling import kld_resample, low_variance_indices
from pipeline.runtime.sensor import Scan, make_sensor_model


def logsumexp(a: np.ndarray) -> float:
    """log(sum(exp(a))) without overflow (scipy's is ~0.6 ms a call at this size: array-API dispatch)."""
    m = float(np.max(a))
    if not np.isfinite(m):
        return m
    return m + math.log(float(np.sum(np.exp(a - m))))


class FilterState(StrEnum):
    TRACKING = "tracking"
    LOST = "lost"
    RELOCALISING = "relocalising"


@dataclass(frozen=True)
class StepResult:
    pose: np.ndarray
    covariance: np.ndarray
    state: FilterState
    particles: int
    updated: bool  # False when the update was gated (not enough motion) or skipped (bad odometry)
    best_likelihood: float  # per-beam relative likelihood of the best particle, (0, 1]
    w_fast: float
    w_slow: float
    clusters: int
    cluster_weight: float


class AdaptiveMCL:
    def __init__(self, lmap: LaserMap, cfg, *, range_max: float,
                 base_from_laser: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        self.map, self.cfg = lmap, cfg
        per_ha = cfg.max_particles_per_ha
        by_area = 0 if per_ha is None else math.ceil(per_ha * lmap.free_area_m2 / 1e4)
        self.max_particles = max(cfg.max_particles, by_area)  # the budget: a large site's search needs more
        self.sensor = make_sensor_model(lmap, cfg.sensor, range_max, base_from_laser)
        self.rng = np.random.default_rng(cfg.seed)
        self.alpha = noise_alphas(cfg.motion)
        self.bin_theta = math.radians(cfg.kld.bin_theta_deg)
        self._odom: np.ndarray | None = None  # odometry at the last applied update
        self._odom_now: np.ndarray | None = None  # the latest odometry reading, applied or not
        self._best = 1.0
        self._judged = False
        self._mode: np.ndarray | None = None  # the last measured belief's settled mode (`_note_mode`)
        self._reset(lmap.sample_free(self.max_particles, self.rng), FilterState.RELOCALISING)

    # ------------------------------------------------------------------------------------ initialisation

    def _set_particles(self, particles: np.ndarray) -> None:
        """A new particle set with equal weights."""
        self.particles = particles
        self.log_w = np.full(len(particles), -math.log(len(particles)))
        self._fresh = np.zeros(len(particles), dtype=bool)  # drawn at random by the last resampling

    def _reset(self, particles: np.ndarray, state: FilterState) -> None:
        self._set_particles(particles)
        self.state = state
        self.w_slow = self.w_fast = 0.0
        self._mode = None
        self._tracked = 0  # judged updates since the filter last began tracking
        self._low_updates = 0
        self._good_updates = 0
        self._force = True
        self._odom = self._odom_now  # the new particles are where the robot is now, not at the last update
        self._estimate = estimate_pose(self.particles, self.weights, self.cfg.kld.bin_xy, self.bin_theta)

    def init_uniform(self, n: int | None = None) -> None:
        """Global localization: particles uniform over the free space."""
        self._reset(self.map.sample_free(n or self.max_particles, self.rng), FilterState.RELOCALISING)

    def init_pose(self, pose, std_xy: float | None = None, std_theta: float | None = None,
                  n: int | None = None, *, check: bool = True) -> None:
        """Tracking from a known pose: a Gaussian around it. The pose must lie in the map's free space
        (`inputs.pose`: a RuntimeInputError otherwise). `check=False` is the camera path's: a pose its scan
        check chose, which off the map or in unknown space starts the filter relocalising, not tracking."""
        c = self.cfg
        pose = inputs.pose(pose, self.map) if check else np.asarray(pose, dtype=np.float64).reshape(3)
        parts = self.map.sample_around(pose[None], np.ones(1), n or self.max_particles,
                                       std_xy or c.init_std_xy, std_theta or math.radians(c.init_std_theta_deg),
                                       self.rng)
        trusted = check or self.map.known(pose[0], pose[1])
        self._reset(parts, FilterState.TRACKING if trusted else FilterState.RELOCALISING)
        if trusted:
            self._tracked = self.cfg.kidnap.trust_updates  # a pose the caller knows is trusted from the start

    def init_candidates(self, poses, weights=None, n: int | None = None, std_theta=None) -> None:
        """Weighted candidate poses (image retrieval's Top-K, weighted 4:3:2:1 by the camera path; equal weights
        when none are given), each with a Gaussian spread (`std_theta`: radians, one or one per pose; default
        init_std_theta_deg)."""
        self._reset(self._around(poses, weights, n or self.max_particles, std_theta), FilterState.RELOCALISING)

    def init_regions(self, cell_region: np.ndarray, weights, n: int | None = None) -> None:
        """Global localization from a prior over parts of the map (seed 001's (room, area) probabilities):
        particles uniform over each region's free cells, as many as its weight says."""
        self._reset(self.map.sample_regions(cell_region, weights, n or self.max_particles, self.rng),
                    FilterState.RELOCALISING)

    def inject(self, poses, weights=None, n: int | None = None, std_theta=None) -> int:
        """Add n particles drawn around candidate poses (the paper: 1000 per step while lost).

        The set grows by n up to max_particles; beyond that the lightest old particles make room. New
        particles get the mean weight, so the next scan decides between them and the old hypotheses.
        """
        n = min(n if n is not None else self.cfg.inject_particles, self.max_particles)
        if n <= 0:
            return 0
        return self._add_particles(self._around(poses, weights, n, std_theta))

    def inject_regions(self, cell_region: np.ndarray, weights, n: int | None = None) -> int:
        """Add n particles spread over labelled parts of the free space (an area prior), as `inject` does."""
        n = min(n if n is not None else self.cfg.inject_particles, self.max_particles)
        if n <= 0:
            return 0
        return self._add_particles(self.map.sample_regions(cell_region, weights, n, self.rng))

    def _add_particles(self, new: np.ndarray) -> int:
        n = len(new)
        room = self.max_particles - n
        if len(self.particles) > room:
            keep = np.argsort(-self.log_w, kind="stable")[:room]
            self.particles, self.log_w, self._fresh = self.particles[keep], self.log_w[keep], self._fresh[keep]
        new_w = logsumexp(self.log_w) - math.log(max(len(self.log_w), 1)) if len(self.log_w) else 0.0
        self.particles = np.vstack([self.particles, new])
        self.log_w = np.r_[self.log_w, np.full(n, new_w)]
        self._fresh = np.r_[self._fresh, np.zeros(n, dtype=bool)]
        self.log_w -= logsumexp(self.log_w)
        if self.state == FilterState.LOST:
            self.state = FilterState.RELOCALISING
        self._force = True
        return n

    def _around(self, poses, weights, n: int, std_theta=None) -> np.ndarray:
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        w = np.ones(len(poses)) if weights is None else np.asarray(weights, dtype=np.float64)
        if len(w) != len(poses) or not np.all(np.isfinite(w)) or w.sum() <= 0 or np.any(w < 0):
            raise ValueError(f"candidate weights {w.tolist()} do not fit {len(poses)} candidate poses")
        std_theta = math.radians(self.cfg.init_std_theta_deg) if std_theta is None else std_theta
        return self.map.sample_around(poses, w, n, self.cfg.init_std_xy, std_theta, self.rng)

    # -------------------------------------------------------------------------------------------- update

    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_w - logsumexp(self.log_w))

    @property
    def estimate(self) -> PoseEstimate:
        return self._estimate

    def update(self, odom, scan: Scan | None) -> StepResult:
        """Apply one odometry reading (x, y, theta in the odometry frame) and, if travel allows, the scan."""
        odom = np.asarray(odom, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(odom)):
            return self._result(False)
        if self._odom is None:
            self._odom = odom
        self._odom_now = odom
        rot1, trans, rot2 = odometry_delta(self._odom, odom)
        turn = abs(float(wrap_angle(rot1 + rot2)))
        moved = trans >= self.cfg.update_min_d or turn >= math.radians(self.cfg.update_min_a_deg)
        if not (moved or self._force):
            return self._result(False)
        settled = self._settled_pose(rot1, trans, rot2)
        self.particles = sample_motion_model_odometry(self.particles, self._odom, odom, self.alpha, self.rng)
        self._odom = odom
        self._force = False
        self._judged = False
        if scan is not None:
            self._measure(scan, settled)
        else:
            self._note_mode()
        self._estimate = estimate_pose(self.particles, self.weights, self.cfg.kld.bin_xy, self.bin_theta)
        self._update_state()
        return self._result(True)

    def _measure(self, scan: Scan, settled: np.ndarray | None) -> None:
        c = self.cfg
        prior = self.weights
        res = (self.sensor.evaluate_skipping if self._skips_beams(prior) else self.sensor.evaluate)(
            self.particles, scan, settled=settled)
        if res.beams_used == 0:
            self._note_mode()
            return
        self.log_w = self.log_w + res.log_likelihood
        self.log_w -= logsumexp(self.log_w)
        self._note_mode()
        if res.beams_judged < c.kidnap.min_beams:  # too little left to tell lost from an unlucky scan
            self._resample(scan)
            return
        self._judged = True
        self._best = float(res.relative_likelihood.max())
        # The belief's average likelihood. While tracking, the particles the last resampling drew at random
        # carry no evidence yet: counting them would lower w_fast, draw more of them, and so on (a map of
        # hectares, 500 particles). While searching they are the search, and their misfit its spur.
        rel = res.relative_likelihood
        if self.state == FilterState.TRACKING and self._fresh.any() and not self._fresh.all():
            informed = ~self._fresh
            w_avg = float(prior[informed] @ rel[informed]) / max(float(prior[informed].sum()), 1e-300)
        else:
            w_avg = float(prior @ rel)
        if self.w_slow == 0.0:
            self.w_slow, self.w_fast = w_avg, w_avg
        else:
            self.w_slow += c.alpha_slow * (w_avg - self.w_slow)
            self.w_fast += c.alpha_fast * (w_avg - self.w_fast)
        low = (self._best < c.kidnap.min_likelihood or res.through_share > c.kidnap.max_through_share
               or (self.w_slow > 0 and self.w_fast / self.w_slow < c.kidnap.fast_slow_ratio))
        self._low_updates = self._low_updates + 1 if low else 0
        self._resample(scan)

    def _skips_beams(self, weights: np.ndarray | None = None) -> bool:
        """Beam skipping (`sensor.beam_skip`); with `sensor.beam_skip_spread_m` set, only while the filter
        tracks one settled cluster (checked on the particles as they are now, injections included;
        `weights`: theirs, when the caller has them already)."""
        s = self.cfg.sensor
        if not s.beam_skip or s.model != "likelihood_field":
            return False
        if s.beam_skip_spread_m is None:
            return True
        if self.state != FilterState.TRACKING:
            return False
        w = self.weights if weights is None else weights
        xy = self.particles[:, :2]
        if self._fresh.any():  # the random draws carry no evidence yet: see _measure
            w, xy = w[~self._fresh], xy[~self._fresh]
            if w.sum() <= 0:
                return False
            w = w / w.sum()
        var = w @ (xy - w @ xy) ** 2
        return bool(np.sqrt(var.sum()) <= s.beam_skip_spread_m)

    def _settled_pose(self, rot1: float, trans: float, rot2: float) -> np.ndarray | None:
        """Where the last measured belief's mode is after this motion, if that mode was settled (`_note_mode`),
        else None: the pose the sensor tells unmapped obstacles by."""
        if self._mode is None or self.state != FilterState.TRACKING or self._tracked < self.cfg.kidnap.trust_updates:
            return None
        x, y, theta = self._mode
        heading = theta + rot1
        return np.array([x + trans * math.cos(heading), y + trans * math.sin(heading), heading + rot2])

    def _note_mode(self) -> None:
        """After a measurement, before resampling (so the augmented MCL's random particles, spread over the
        map with no evidence yet, do not count): the weighted particles within 1 m of the heaviest. Their
        mean is the settled mode when they hold kidnap.converged_share of the weight within
        kidnap.converged_std_m of position std."""
        k = self.cfg.kidnap
        pose, share, std = mode_near_best(self.particles, self.log_w, 1.0)  # log_w is normalised here
        self._mode = pose if share >= k.converged_share and std <= k.converged_std_m else None

    def _resample(self, scan: Scan) -> None:
        c = self.cfg
        w = self.weights
        if c.method == "mcl":
            self._set_particles(self.particles[low_variance_indices(w, self.max_particles, self.rng)])
        else:
            self._set_particles(kld_resample(self.particles, w, min_n=c.min_particles, max_n=self.max_particles,
                                             err=c.kld.err, delta=c.kld.delta, bin_xy=c.kld.bin_xy,
                                             bin_theta=self.bin_theta, rng=self.rng))
        n = len(self.particles)
        if c.method == "amcl" and self.w_slow > 0:
            p_random = max(0.0, 1.0 - self.w_fast / self.w_slow)
            swap = self.rng.random(n) < p_random
            if swap.any():
                self.particles[swap] = self.map.sample_free(int(swap.sum()), self.rng)
                self._fresh = swap
        elif c.method == "mixture" and c.mixture_share > 0:
            self._mix_dual(scan)

    def _mix_dual(self, scan: Scan) -> None:
        """Replace a share of the set by dual-proposal draws weighted by the prior belief's density."""
        from scipy.spatial import cKDTree

        c = self.cfg
        n = len(self.particles)
        m = max(1, int(round(c.mixture_share * n)))
        pool = self.map.sample_free(8 * m, self.rng)
        lik = self.sensor.evaluate(pool, scan).log_likelihood
        dual = pool[low_variance_indices(np.exp(lik - lik.max()), m, self.rng)]
        # Prior density at the dual draws: Gaussian kernel over the forward particles (x, y; 0.5 m bandwidth).
        tree = cKDTree(self.particles[:, :2])
        bandwidth = 0.5
        counts = np.array([len(v) for v in tree.query_ball_point(dual[:, :2], 2 * bandwidth)], dtype=np.float64)
        density = counts / n + 1e-12
        keep = self.rng.permutation(n)[: n - m]
        self.particles = np.vstack([self.particles[keep], dual])
        w = np.r_[np.full(n - m, (1.0 - c.mixture_share) / (n - m)), c.mixture_share * density / density.sum()]
        self.log_w = np.log(w)
        self._fresh = np.zeros(n, dtype=bool)

    def _update_state(self) -> None:
        k = self.cfg.kidnap
        est = self._estimate
        tight = est.cluster_weight >= k.converged_share and est.std_xy <= k.converged_std_m
        # Lost: the scan has disagreed with the best particle for several updates while the belief is
        # committed (tracking, or collapsed onto one wrong cluster during a search). A spread belief that
        # fits badly is still searching and is left to the random particles. A tracked belief that odometry
        # took off the map or into unknown space is lost at once: no robot is there, whatever the scan says.
        astray = self.state == FilterState.TRACKING and not self.map.known(est.pose[0], est.pose[1])
        if astray or (self._low_updates >= k.updates and (self.state == FilterState.TRACKING or tight)):
            self.state = FilterState.LOST
            self._good_updates = 0
            self._low_updates = 0
            if k.reinit_uniform:
                n_keep = min(k.keep_particles, len(self.particles), self.max_particles)
                kept = self.particles[np.argsort(-self.log_w, kind="stable")[:n_keep]]
                self._set_particles(np.vstack([kept, self.map.sample_free(self.max_particles - n_keep,
                                                                          self.rng)]))
                self._force = True
            return
        if self.state != FilterState.TRACKING:
            if not self._judged:  # no evidence either way (kidnap.min_beams)
                return
            good = (tight and self._best >= k.min_likelihood and self._low_updates == 0
                    and self.map.known(est.pose[0], est.pose[1]))
            # One tight update can be a wrong mode that happened to fit; several in a row rarely are.
            self._good_updates = self._good_updates + 1 if good else 0
            if self._good_updates >= k.updates:
                self.state = FilterState.TRACKING
                self._tracked = 0
        elif self._judged:
            self._tracked += 1

    def _result(self, updated: bool) -> StepResult:
        """The estimate at the latest odometry: between updates the last update's pose carried by the
        odometry since (what nav2 publishes as map -> odom composed with odom -> base)."""
        e = self._estimate
        pose = e.pose.copy()
        if not updated and self._odom is not None and self._odom_now is not None:
            since = compose2d(inverse2d(self._odom[None]), self._odom_now[None])  # odometry since the update
            pose = compose2d(pose[None], since)[0]
        return StepResult(pose, e.covariance.copy(), self.state, len(self.particles), updated, self._best,
                          self.w_fast, self.w_slow, e.clusters, e.cluster_weight)
