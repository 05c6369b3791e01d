"""The camera path: how camera evidence enters the laser filter (docs/runtime.md).

Sources hand ranked poses: the current image's retrieval, the image sequence's once its buffer is full,
simulated candidates when `siteloc localize` replays laser logs. The filter's state decides what
happens to them, one update at a time:

- no belief yet: the filter starts around the poses that fit the first scan best (or, with seed
  001's prior, over the free space of the image's most probable areas);
- not tracking (lost or relocalising): particles go around the poses that fit the scan best;
- not lost: far poses that fit the scan are held as hypotheses and collect evidence against the
  estimate (`hypotheses.Hypotheses`); one that wins replaces the belief.

"Fit the scan best" is one check (`scancheck.check_candidates`): each pose refined against the scan,
ordered by its log-likelihood plus the source's rank prior. Nothing here knows where the poses came
from, so the bundle's `Localizer` and the laser-log replays run the same path.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.retrieval.search import weighted_candidates
from pipeline.runtime.amcl import AdaptiveMCL, FilterState, StepResult
from pipeline.runtime.hypotheses import Hypotheses, Weighing


@dataclass(frozen=True)
class CameraStep:
    result: StepResult  # the filter's state after the update (and after a won hypothesis replaced the belief)
    candidates: np.ndarray | None  # (K, 4) x, y, theta, weight seeded or injected at this update
    source: str | None  # image, sequence, sequence+image, hypothesis, area_prior, image+area_prior


class CameraPath:
    """One filter's camera path. `rank_image(frame)` -> (N, 3) ranked poses of a frame, best first;
    `sequence`: a `SequenceRelocaliser` (push, keep_last, ready, ranked) or None; `areas(frame)` ->
    (cell_region, weights) of seed 001's prior, or None; `mode`: what re-localizes (image, sequence,
    both: `filter.relocalise_with` resolved)."""

    def __init__(self, filt: AdaptiveMCL, cfg, candidate_weights, *, rank_image: Callable[[object], np.ndarray],
                 range_max: float, base_from_laser=(0.0, 0.0, 0.0), mode: str = "image", sequence=None,
                 areas: Callable | None = None):
        self.cfg, self.weights = cfg, tuple(candidate_weights)
        self.rank_image, self.sequence, self.areas, self.mode = rank_image, sequence, areas, mode
        self.range_max, self.base_from_laser = range_max, tuple(base_from_laser)
        self.reset(filt)

    def reset(self, filt: AdaptiveMCL, cfg=None, *, mode: str | None = None) -> None:
        """Start over with a new filter (the next step seeds it), and new settings if given."""
        self.filter, self.map = filt, filt.map
        self.cfg = cfg if cfg is not None else self.cfg
        self.mode = mode if mode is not None else self.mode
        self.started = False
        self.seeded_by_camera = False
        self.awaiting_sequence = False  # lost, and the sequence has not yet brought the filter back
        self._was_lost = False
        self._confirmed = 0
        self._weighed = 0  # updates with a frame and a scan, for camera.every
        self.hypotheses = Hypotheses()
        # Its own stream: weighing hypotheses leaves the filter's draws as they would be without it.
        self._rng = np.random.default_rng((self.cfg.seed, 0xE71D))
        self._ranked_for, self._ranked = None, None
        if self.sequence is not None:
            self.sequence.keep_last(0)

    @property
    def verifier(self):
        """The sensor model that scores checked poses (`filter.scan_check.model`): the filter's, or a beam
        model on the same map and sensor settings (built once; its range table is cached on disk)."""
        if self.cfg.scan_check.model == "filter":
            return self.filter.sensor
        from pipeline.runtime.sensor import make_sensor_model

        sensor = self.cfg.sensor
        if getattr(self, "_verifier_for", None) != (sensor, id(self.map)):  # rebuilt only on a change
            cfg = sensor.model_copy(update={"model": "beam", "beam_skip": False})
            self._verifier = make_sensor_model(self.map, cfg, self.range_max, self.base_from_laser)
            self._verifier_for = (sensor, id(self.map))
        return self._verifier

    def ranked(self, frame) -> np.ndarray:
        """`rank_image(frame)`, computed once per step however many parts of the path ask for it."""
        if self._ranked_for is not frame:
            self._ranked, self._ranked_for = np.asarray(self.rank_image(frame), dtype=np.float64), frame
        return self._ranked

    def proposals(self, sources: tuple[str, ...], frame, scan) -> tuple[np.ndarray, np.ndarray]:
        """Where particles go: (K, 4) x, y, theta, weight and (K,) each one's heading spread (radians).

        Each source's Top-pool (`scan_check.pool`) is checked against `scan` together, each source's
        rank as a prior (`scan_check.rank_prior`), and the K (K = len(candidate_weights)) that fit best,
        at their best-fitting pose, are weighted as retrieval's Top-K would be. With pool 0 or no usable
        beam: each source's own Top-K (with both sources, at half weight each)."""
        from pipeline.runtime.scancheck import check_candidates

        sc, cfg = self.cfg.scan_check, self.cfg
        k = max(sc.pool, len(self.weights))
        pools, spreads, priors = [], [], []
        for source in sources:
            pool = self.sequence.ranked(k) if source == "sequence" else self.ranked(frame)
            deg = cfg.sequence_heading_std_deg if source == "sequence" else None
            pools.append(pool[: sc.pool] if sc.pool else pool)
            spreads.append(np.full(len(pools[-1]), math.radians(deg if deg is not None else cfg.init_std_theta_deg)))
            priors.append(-sc.rank_prior * np.log1p(np.arange(len(pools[-1]))))
        if sc.pool and scan is not None:
            pool, spread = np.vstack(pools), np.concatenate(spreads)
            checked = check_candidates(self.verifier, self.map, pool, scan, keep=len(self.weights),
                                       samples=sc.samples, std_xy=cfg.init_std_xy, std_theta=spread,
                                       rng=self.filter.rng, log_prior=np.concatenate(priors), rounds=sc.rounds)
            if checked is not None:
                return weighted_candidates(checked.poses, self.weights), spread[checked.rank]
        cands = [weighted_candidates(p, self.weights) for p in pools]
        out = np.vstack(cands)
        out[:, 3] /= len(cands)
        return out, np.concatenate([sp[: len(c)] for sp, c in zip(spreads, cands, strict=True)])

    @property
    def weighing(self) -> Weighing:
        cfg, cam = self.cfg, self.cfg.camera
        return Weighing(pool=max(cfg.scan_check.pool, len(self.weights)), samples=cfg.scan_check.samples,
                        rounds=cfg.scan_check.rounds, std_xy=cfg.init_std_xy,
                        std_theta=math.radians(cfg.init_std_theta_deg), min_distance_m=cam.min_distance_m,
                        distinct=cam.distinct, laser_nats=cam.laser_nats, min_fit=cfg.kidnap.min_likelihood,
                        radius_m=cam.rank_radius_m, heading_rad=math.radians(cam.rank_heading_deg),
                        max_rank=cam.max_rank, min_checks=cam.min_checks)

    def step(self, odom, scan, frame=None) -> CameraStep:
        """One update: seed or inject from the sources as the filter's state asks, update the filter with
        `odom` and `scan`, then weigh the hypotheses. `frame`: the camera's frame at this step, or None."""
        cfg, f = self.cfg, self.filter
        self._ranked_for = None  # a new frame: ranked (at most) once in this step
        cands, source = None, None
        use_sequence = self.mode != "image" and self.sequence is not None
        state = f.state  # as the last update left it
        if use_sequence and self.started and state == FilterState.LOST and not self._was_lost:
            # Just declared lost (the filter may stay lost for several updates until something is injected):
            # the frames seen while the kidnap rule was counting were taken where the robot is now.
            self.sequence.keep_last(cfg.kidnap.updates)
            self.awaiting_sequence = True
        lost_before = self._was_lost
        self._was_lost = self.started and state == FilterState.LOST
        if use_sequence and frame is not None:
            self.sequence.push(frame)
        starting = not self.started
        if starting:
            if frame is not None and cfg.seed_with == "area_prior":
                f.init_regions(*self.areas(frame))  # seed 001: whole areas, not poses
                self.seeded_by_camera, source = True, "area_prior"
            elif frame is not None:
                cands, spread = self.proposals(("image",), frame, scan)
                f.init_candidates(cands[:, :3], cands[:, 3], std_theta=spread)
                self.seeded_by_camera, source = True, "image"
            else:
                f.init_uniform()
            self.started = True
        else:
            cands, source = self._inject(state, frame, scan, lost_before)
        res = f.update(odom, scan)
        won = self._weigh(odom, res, frame, scan) if cfg.camera.every and res.updated and not starting else None
        if won is not None:  # the belief was replaced: report the new one
            cands, source = np.r_[won, 1.0][None], "hypothesis"
            est = f.estimate
            res = StepResult(est.pose.copy(), est.covariance.copy(), f.state, len(f.particles), True,
                             res.best_likelihood, res.w_fast, res.w_slow, est.clusters, est.cluster_weight)
        return CameraStep(res, cands, source)

    def _inject(self, state: FilterState, frame, scan, lost_before: bool):
        """While the filter is not tracking: particles around the sources' best-fitting poses."""
        cfg, f = self.cfg, self.filter
        if self.awaiting_sequence and state == FilterState.TRACKING:
            # Tracking again, but a wrong twin of the place can fit the laser as well as the right one:
            # the sequence keeps proposing for `sequence_confirm_steps` more steps.
            self._confirmed += 1
            if self._confirmed > cfg.sequence_confirm_steps:
                self.awaiting_sequence = False
        elif self.awaiting_sequence:
            self._confirmed = 0
        sources = ["sequence"] if self.awaiting_sequence and self.sequence.ready else []
        lost = state == FilterState.LOST
        image_relocalises = self.mode != "sequence"
        if frame is not None and (
                (not sources and ((lost and image_relocalises) or not self.seeded_by_camera))
                or (cfg.inject_while_relocalising and image_relocalises
                    and (state == FilterState.RELOCALISING or sources))):
            sources.append("image")
        cands, source = None, None
        if sources:
            cands, spread = self.proposals(tuple(sources), frame, scan)
            source = "+".join(sources)
            f.inject(cands[:, :3], cands[:, 3], std_theta=spread)
            self.seeded_by_camera = True
        if cfg.inject_areas and frame is not None and lost and not lost_before:
            # Seed 001's prior names areas where the pose candidates may all be wrong twins.
            f.inject_regions(*self.areas(frame))
            source = "image+area_prior" if source == "image" else (source or "area_prior")
        return cands, source

    def _weigh(self, odom, res: StepResult, frame, scan) -> np.ndarray | None:
        """While the filter is not lost: the hypotheses checked against the estimate; a winner replaces
        the belief (injecting beside a cluster that sits on the laser's peak would leave it the belief)."""
        cam = self.cfg.camera
        self.hypotheses.follow(odom, res.pose, tracking=res.state == FilterState.TRACKING, jump_m=cam.min_distance_m)
        # Lost: the estimate is no hypothesis, but the ones held are followed on (one may be the truth).
        if res.state == FilterState.LOST or frame is None or scan is None:
            return None
        self._weighed += 1
        if self._weighed % cam.every:
            return None
        settled = cam.settled_updates is not None and self.hypotheses.age >= cam.settled_updates
        won = self.hypotheses.check(self.verifier, self.map, res.pose, self.ranked(frame), scan, self.weighing,
                                    threshold=cam.settled_threshold if settled else cam.threshold, rng=self._rng)
        if won is None:
            return None
        self.filter.init_pose(won, check=False)  # the scan chose it; off the map it only relocalises
        self.awaiting_sequence = False  # the evidence is the confirmation the sequence was waiting for
        return won
