"""Laser sensor models, vectorised over particles x beams (Probabilistic Robotics, sections 6.3 and 6.4).

Both return a proper log-likelihood per particle: the sum over the used beams of log p(z_k | x, m),
divided by `temperature` (>= 1 flattens the product of correlated beams). They also return the
per-beam geometric mean likelihood exp(mean log p) relative to a perfect match, a number in (0, 1]
that does not depend on how many beams were used: the augmented MCL averages and the kidnap rule read it.
Given a settled belief's pose, the likelihood field leaves out of that number the beams that end well
short of the map's first wall seen from there (`unmapped_margin_m`): an unmapped obstacle in front of the
laser is not evidence that the robot is lost, a beam through a wall is.

Scans follow REP 117: +inf is "no return within range" (a max-range reading), NaN and -inf are
invalid and skipped, readings below `range_min` are skipped. Beams are subsampled evenly to
`max_beams` (nav2's max_beams) before anything else.

- Likelihood field: an endpoint's log p = log(z_hit N(d; 0, sigma_hit) + z_rand / range_max), d its
  distance to the nearest occupied cell (capped at max_distance; off-map endpoints are "far"). The
  value is precomputed per cell, so an update is one lookup per endpoint. Max-range readings carry no
  endpoint and are skipped (as nav2).
- Beam model: the mixture of hit (Gaussian around the ray-cast range), short (exponential, with the
  1 / (1 - exp(-lambda z*)) normaliser), max and random. Expected ranges come from a table precomputed
  once per map (exact casts from every free cell's centre in `table_angles` headings; the particle's
  cell and heading bin pick the entry, as RangeLibc's lookup table does) or, with ray_cast = march,
  from an exact cast per particle and beam (slower; no table memory).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from pipeline.runtime import kernels
from pipeline.runtime.grid import LaserMap

SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class Scan:
    """One laser reading in the laser frame: beam k at angle_min + k * angle_increment."""

    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_max: float

    @property
    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges))


@dataclass(frozen=True)
class SensorResult:
    log_likelihood: np.ndarray  # (N,) sum of log p over used beams / temperature
    relative_likelihood: np.ndarray  # (N,) per-beam geometric mean likelihood / a perfect match's, in (0, 1]
    beams_used: int  # beams in log_likelihood
    beams_judged: int  # beams in relative_likelihood
    through_share: float = 0.0  # of the beams, those a settled belief sees pass its walls (`settled_view`)


@functools.lru_cache(maxsize=64)
def subsample(n_beams: int, max_beams: int) -> np.ndarray:
    """Indices of at most max_beams beams spread evenly over the scan, first and last included (read-only:
    memoised, every scan of a laser asks the same)."""
    idx = np.arange(n_beams) if n_beams <= max_beams else np.unique(
        np.round(np.linspace(0, n_beams - 1, max_beams)).astype(np.int64))
    idx.flags.writeable = False
    return idx


def subsampled(scan: Scan, max_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """(ranges as float64, angles) of the beams `subsample` keeps, before any validity test."""
    idx = subsample(len(scan.ranges), max_beams)
    return (np.asarray(scan.ranges, dtype=np.float64)[idx],
            scan.angle_min + scan.angle_increment * idx.astype(np.float64))


def laser_poses(map_from_base: np.ndarray, base_from_laser: tuple[float, float, float]) -> np.ndarray:
    """map_from_laser (N, 3) = map_from_base * base_from_laser."""
    lx, ly, lyaw = base_from_laser
    if lx == 0.0 and ly == 0.0 and lyaw == 0.0:
        return map_from_base
    c, s = np.cos(map_from_base[:, 2]), np.sin(map_from_base[:, 2])
    return np.column_stack([map_from_base[:, 0] + c * lx - s * ly, map_from_base[:, 1] + s * lx + c * ly,
                            map_from_base[:, 2] + lyaw])


class LikelihoodFieldModel:
    def __init__(self, lmap: LaserMap, cfg, range_max: float,
                 base_from_laser: tuple[float, float, float] = (0.0, 0.0, 0.0), backend: str = "auto"):
        if cfg.max_distance != lmap.max_distance:
            raise ValueError(f"map distance field capped at {lmap.max_distance} m, model wants {cfg.max_distance}")
        self.map, self.cfg, self.range_max = lmap, cfg, float(range_max)
        self.base_from_laser, self.backend = tuple(base_from_laser), backend
        d = lmap.distance_padded.astype(np.float64)
        p = cfg.z_hit * np.exp(-0.5 * (d / cfg.sigma_hit) ** 2) / (SQRT_2PI * cfg.sigma_hit) + cfg.z_rand / range_max
        self.field = np.log(p).astype(np.float32)
        self.log_best = math.log(cfg.z_hit / (SQRT_2PI * cfg.sigma_hit) + cfg.z_rand / range_max)
        self.log_floor = float(self.field.min())

    def beams(self, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """(ranges, angles) of the used beams: subsampled, finite, in [range_min, range_max)."""
        r, a = subsampled(scan, self.cfg.max_beams)
        ok = self._used(r, scan)
        return r[ok], a[ok]

    def _used(self, r: np.ndarray, scan: Scan) -> np.ndarray:
        """Which subsampled readings `beams` keeps."""
        return np.isfinite(r) & (r >= self.cfg.range_min) & (r < min(scan.range_max, self.range_max))

    def evaluate(self, particles: np.ndarray, scan: Scan, settled: np.ndarray | None = None) -> SensorResult:
        return self._evaluate(particles, scan, skip=False, settled=settled)

    @functools.cached_property
    def safe(self) -> np.ndarray:
        """Safe ray steps (cells) from the capped distance field, for `settled_view` (see kernels.safe_steps)."""
        d = self.map.distance_padded[1:-1, 1:-1] * np.float32(1.0 / self.map.resolution)
        return d - np.float32(math.sqrt(2.0))

    def settled_view(self, settled: np.ndarray, scan: Scan) -> tuple[np.ndarray, float]:
        """The scan against the map's first walls seen from the base pose `settled` (x, y, theta): (the used
        beams (`beams`) ending more than `unmapped_margin_m` short of it, bool; the share of the subsampled
        beams that pass it by as much, or return nothing where it lies in range: through walls)."""
        r, a = subsampled(scan, self.cfg.max_beams)
        short, through = self._settled_view(settled, r, a, scan)
        return short[self._used(r, scan)], through

    def _settled_view(self, settled: np.ndarray, r: np.ndarray, a: np.ndarray, scan: Scan) -> tuple[np.ndarray, float]:
        """`settled_view` on the subsampled readings (r, a), its first part over all of them."""
        far = min(scan.range_max, self.range_max)
        laser = laser_poses(np.asarray(settled, dtype=np.float64).reshape(1, 3), self.base_from_laser)
        expected = kernels.cast_rays(laser, a, self.map.occupied, self.safe, self.map.resolution,
                                     (self.map.origin_x, self.map.origin_y), self.range_max)[0]
        m = self.cfg.unmapped_margin_m
        with np.errstate(invalid="ignore"):  # NaN readings compare False: neither short nor through
            valid = ~np.isnan(r) & (r >= self.cfg.range_min)  # -inf is below range_min
            seen = np.where(r < far, r, far)  # no return (+inf, >= range_max): seen to the range limit
            through = valid & (expected < far - m) & (seen > expected + m)
            return r < expected - m, float(through.sum() / max(int(valid.sum()), 1))

    def evaluate_skipping(self, particles: np.ndarray, scan: Scan, settled: np.ndarray | None = None) -> SensorResult:
        """`evaluate` with nav2 amcl's beam skipping (`cfg.beam_skip_*`): a beam whose endpoint lies within
        beam_skip_distance of an obstacle for fewer than beam_skip_threshold of the particles is left out of
        the weights (it most likely hit something the map does not have), unless beam_skip_error_threshold of
        the beams would go (then the belief, not the beams, is wrong, unless `settled` finds them ending short
        of its map: then those go, a crowd all round leaves nothing to weigh). The relative likelihood, which the
        kidnap rule reads, does not follow the skipping: a beam the particles disagree with may be a beam
        through a wall, which only a kidnapping explains (`settled` leaves out the unmapped ones)."""
        return self._evaluate(particles, scan, skip=True, settled=settled)

    def _evaluate(self, particles: np.ndarray, scan: Scan, *, skip: bool,
                  settled: np.ndarray | None = None) -> SensorResult:
        r_all, a_all = subsampled(scan, self.cfg.max_beams)
        used = self._used(r_all, scan)
        r, a = r_all[used], a_all[used]
        n = len(particles)
        if len(r) == 0:  # nothing seen: the scan says nothing about the pose
            return SensorResult(np.zeros(n), np.ones(n), 0, 0)
        poses = laser_poses(particles, self.base_from_laser)
        bx, by, origin = r * np.cos(a), r * np.sin(a), (self.map.origin_x, self.map.origin_y)
        unmapped, through = None, 0.0
        if settled is not None and self.cfg.unmapped_margin_m is not None:
            short, through = self._settled_view(settled, r_all, a_all, scan)
            unmapped = short[used]
        # One pass: the sum over the beams that judge the pose (all but a settled belief's unmapped ones)
        # and over all of them.
        fit, total = kernels.field_sums(poses, bx, by, unmapped, self.field, self.map.resolution, origin,
                                        backend=self.backend)
        judged = len(r) if unmapped is None else len(r) - int(unmapped.sum())
        rel = np.exp(fit / judged - self.log_best) if judged else np.ones(n)
        keep = None
        if skip:
            agree = kernels.beam_agreement(poses, bx, by, self.map.distance_padded, self.cfg.beam_skip_distance,
                                           self.map.resolution, origin, backend=self.backend)
            keep = agree >= self.cfg.beam_skip_threshold
            if 1.0 - keep.mean() >= self.cfg.beam_skip_error_threshold:
                # The particles disagree with nearly every beam: the belief is wrong, or something the map
                # lacks fills the view. A settled belief tells them apart: only its unmapped beams go.
                keep = None if unmapped is None else ~unmapped
        if keep is None or keep.all():
            return SensorResult(total / self.cfg.temperature, rel, len(r), judged, through)
        if unmapped is not None and np.array_equal(keep, ~unmapped):
            kept = fit
        else:
            kept = kernels.field_sum(poses, bx[keep], by[keep], self.field, self.map.resolution, origin,
                                     backend=self.backend)
        return SensorResult(kept / self.cfg.temperature, rel, int(keep.sum()), judged, through)


_TABLES: dict[tuple, tuple[np.ndarray, np.ndarray, float]] = {}


def range_table(lmap: LaserMap, n_angles: int, range_max: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The map's precomputed range table, memoised in the process and cached on disk (arrays, no pickle).

    Cache: $SITELOC_CACHE/range-tables (default ~/.cache/siteloc), keyed by the map's fingerprint, the
    heading bins and range_max; a table is about free cells x n_angles x 2 bytes.
    """
    import os
    from pathlib import Path

    key = (lmap.fingerprint(), int(n_angles), float(range_max))
    if key in _TABLES:
        return _TABLES[key]
    root = Path(os.environ.get("SITELOC_CACHE", Path.home() / ".cache" / "siteloc")) / "range-tables"
    path = root / f"{key[0][:24]}-{key[1]}-{key[2]:g}.npz"
    built = None
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                built = (z["cell_index"], z["table"], float(z["unit"]))
            if built[0].shape != lmap.free.shape:
                built = None
        except (OSError, ValueError, KeyError):
            built = None
    if built is None:
        built = kernels.build_range_table(lmap.occupied, lmap.free, lmap.resolution, (lmap.origin_x, lmap.origin_y),
                                          n_angles, range_max)
        try:
            from pipeline.io.atomic import atomic_file

            root.mkdir(parents=True, exist_ok=True)
            with atomic_file(path, "wb") as fh:
                np.savez(fh, cell_index=built[0], table=built[1], unit=np.float64(built[2]))
        except OSError:
            pass  # a read-only home: the table is still used, just rebuilt next time
    _TABLES[key] = built
    return built


class BeamModel:
    def __init__(self, lmap: LaserMap, cfg, range_max: float,
                 base_from_laser: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        self.map, self.cfg, self.range_max = lmap, cfg, float(range_max)
        self.base_from_laser = tuple(base_from_laser)
        self.table = range_table(lmap, cfg.table_angles, range_max) if cfg.ray_cast == "table" else None
        self.inv_short = kernels.short_normalisers(self.table[2], cfg.lambda_short) if self.table else None
        # Best case: a hit exactly at the expected range, short-reading density at that range ignored.
        self.log_best = math.log(cfg.z_hit / (SQRT_2PI * cfg.sigma_hit) + cfg.z_rand / range_max + cfg.z_short *
                                 cfg.lambda_short)

    def beams(self, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """(ranges, angles) of the used beams; +inf and readings >= range_max become max-range readings."""
        r, a = subsampled(scan, self.cfg.max_beams)
        r = np.where(np.isposinf(r), self.range_max, r)
        ok = np.isfinite(r) & (r >= self.cfg.range_min)
        return np.minimum(r[ok], self.range_max), a[ok]

    @functools.cached_property
    def safe(self) -> np.ndarray:
        """Safe steps of the exact caster; only `ray_cast: march` (and `expected`) need them."""
        return kernels.safe_steps(self.map.occupied)

    def expected(self, particles: np.ndarray, angles: np.ndarray) -> np.ndarray:
        poses = laser_poses(particles, self.base_from_laser)
        return kernels.cast_rays(poses, angles, self.map.occupied, self.safe, self.map.resolution,
                                 (self.map.origin_x, self.map.origin_y), self.range_max)

    def probabilities(self, z: np.ndarray, z_star: np.ndarray) -> np.ndarray:
        """p(z | z*) of the four-part mixture, elementwise."""
        c = self.cfg
        zmax = self.range_max
        is_max = z >= zmax
        p_hit = np.where(is_max, 0.0, np.exp(-0.5 * ((z - z_star) / c.sigma_hit) ** 2) / (SQRT_2PI * c.sigma_hit))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            eta = 1.0 / -np.expm1(-c.lambda_short * z_star)
            p_short = np.where((z < z_star) & ~is_max, eta * c.lambda_short * np.exp(-c.lambda_short * z), 0.0)
        p_short = np.nan_to_num(p_short, nan=0.0, posinf=0.0)
        p_rand = np.where(is_max, 0.0, 1.0 / zmax)
        return c.z_hit * p_hit + c.z_short * p_short + c.z_max * is_max + c.z_rand * p_rand

    def evaluate(self, particles: np.ndarray, scan: Scan, settled: np.ndarray | None = None) -> SensorResult:
        """Weights and relative likelihoods; `settled` is ignored: p_short explains unmapped obstacles here."""
        z, a = self.beams(scan)
        n = len(particles)
        if len(z) == 0:
            return SensorResult(np.zeros(n), np.ones(n), 0, 0)
        if self.table is not None:
            cell_index, table, unit = self.table
            logp = kernels.beam_table_loglik(laser_poses(particles, self.base_from_laser), a, z, cell_index, table,
                                             unit, self.map.resolution, (self.map.origin_x, self.map.origin_y),
                                             self.range_max, self.cfg, self.inv_short)
        else:
            z_star = self.expected(particles, a)
            logp = np.log(np.maximum(self.probabilities(z[None, :], z_star), 1e-300)).sum(axis=1)
        rel = np.exp(np.minimum(logp / len(z) - self.log_best, 0.0))
        return SensorResult(logp / self.cfg.temperature, rel, len(z), len(z))


def make_sensor_model(lmap: LaserMap, cfg, range_max: float, base_from_laser=(0.0, 0.0, 0.0)):
    if cfg.model == "beam":
        return BeamModel(lmap, cfg, range_max, base_from_laser)
    return LikelihoodFieldModel(lmap, cfg, range_max, base_from_laser)
