"""Occupancy grid mapping with known poses (Probabilistic Robotics ch. 9), vectorised in numpy.

Every scan updates each cell at most once, in log-odds: + `log_odds_hit` for a cell holding the
endpoint of a valid return, - `log_odds_miss` for a cell a valid beam passes through on its way there
(a hit overrides a miss of the same scan), clamped to +-`log_odds_clamp` after every scan, so a map
stays revisable and the result does not depend on the batch size. Scans are applied in log order.

Free space comes from exact ray traversal (the cells of Amanatides & Woo's DDA): a beam passes its
start cell and every cell entered where it crosses a grid line; the crossings of all beams of a batch
are generated at once (per-beam counts expanded with np.repeat / cumsum), cells are de-duplicated per
scan with one sort, `chunk_scans` scans per batch. No Python loop runs per beam. (Sampling the beam
every resolution/2 instead would skip ~15 % of the cells a diagonal beam clips at a corner.)

Valid returns are finite readings with 0 < r < range_max and r <= `max_range_m`. **No-return beams
(r >= range_max) clear nothing**: a missing echo may be glass, a black surface or a grazing angle, not
free space, and clearing along 40 m of it would erase walls seen from elsewhere. Returns beyond
`max_range_m` are not used at all (long readings are the least accurate).

Cells never observed stay unknown (-1); observed cells are occupied if sigmoid(L) > occupied_thresh,
free if sigmoid(L) < free_thresh, unknown otherwise (the map_server trinary semantics).

A grid larger than MAX_MAP_CELLS (50 M cells, ~1 GB while mapping) is refused with `MapTooLargeError`
before it is allocated: one corrupt pose far from the rest would otherwise ask for tens of GB.
"""

from __future__ import annotations

import numpy as np

from pipeline.config import MappingConfig
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap

#: Upper bound on traversed cells held in memory at once (about 16 MB per float64 array), so dense,
#: long-range scans (csail: 361 beams to 30 m) do not exhaust a small machine's memory.
MAX_CELLS_PER_BATCH = 2_000_000
#: Upper bound on a map's cells, checked before the grid is allocated: mapping holds ~20 bytes per cell
#: (log-odds, probabilities, masks), so this is ~1 GB, e.g. 350 x 350 m at 0.05 m. The real logs need at
#: most 2.0 M cells (csail, 58 x 87 m); one corrupt pose at x = 1e7 would need 10^11.
MAX_MAP_CELLS = 50_000_000


class MapTooLargeError(ValueError):
    """The grid that would cover the poses and endpoints exceeds MAX_MAP_CELLS; nothing was allocated."""

    def __init__(self, width_m: float, height_m: float, resolution: float):
        self.width_m, self.height_m, self.resolution = width_m, height_m, resolution
        self.cells = (width_m / resolution) * (height_m / resolution)
        super().__init__(
            f"the map would be {width_m:.4g} x {height_m:.4g} m = {self.cells:.3g} cells at {resolution:g} m, "
            f"more than the {MAX_MAP_CELLS:,} cells allowed ({max_side_m(resolution):.4g} x "
            f"{max_side_m(resolution):.4g} m at {resolution:g} m)"
        )


def max_side_m(resolution: float) -> float:
    """Side of the largest square map allowed at `resolution` (metres)."""
    return float(np.sqrt(MAX_MAP_CELLS)) * resolution


def check_map_size(width_m: float, height_m: float, resolution: float) -> None:
    """Raise MapTooLargeError unless a width_m x height_m grid fits in MAX_MAP_CELLS (non-finite never fits)."""
    cells = (width_m / resolution) * (height_m / resolution)
    if not np.isfinite(cells) or cells > MAX_MAP_CELLS:
        raise MapTooLargeError(width_m, height_m, resolution)


def valid_returns(ranges: np.ndarray, range_max: float, max_range: float | None = None) -> np.ndarray:
    """Boolean mask of readings that are real echoes (and within `max_range` if given)."""
    r = np.asarray(ranges, dtype=np.float64)
    ok = np.isfinite(r) & (r > 0) & (r < range_max)
    if max_range is not None:
        ok &= r <= max_range
    return ok


def beam_endpoints(
    poses: np.ndarray, ranges: np.ndarray, angle_min: float, angle_increment: float
) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame (x, y) of every beam's endpoint, each (N, B); `poses` are map_from_laser (N, 3)."""
    poses = np.asarray(poses, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    world = poses[:, 2:3] + (angle_min + angle_increment * np.arange(r.shape[1]))[None, :]
    return poses[:, 0:1] + r * np.cos(world), poses[:, 1:2] + r * np.sin(world)


def _grid_frame(xs: np.ndarray, ys: np.ndarray, cfg: MappingConfig) -> tuple[float, float, int, int]:
    """(origin_x, origin_y, width, height): the points' bounding box plus the margin, snapped to cells;
    MapTooLargeError (before anything is allocated) if that grid exceeds MAX_MAP_CELLS."""
    res = cfg.resolution
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 - (-1e308) is inf: refused below
        ox = float(np.floor((xs.min() - cfg.margin_m) / res) * res)
        oy = float(np.floor((ys.min() - cfg.margin_m) / res) * res)
        width = float(np.ceil((xs.max() + cfg.margin_m - ox) / res)) + 1
        height = float(np.ceil((ys.max() + cfg.margin_m - oy) / res)) + 1
    check_map_size(width * res, height * res, res)
    return round(ox, 9), round(oy, 9), int(width), int(height)


def _inside(frame: tuple[float, float, int, int], res: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    ox, oy, width, height = frame
    u, v = (x - ox) / res, (y - oy) / res
    return (u >= 0) & (u < width) & (v >= 0) & (v < height)


def _batches(cells_per_scan: np.ndarray, chunk_scans: int) -> list[tuple[int, int]]:
    """[start, stop) scan ranges of at most `chunk_scans` scans and (unless one scan alone has more)
    MAX_CELLS_PER_BATCH traversed cells."""
    out, start, total = [], 0, 0
    for i, n in enumerate(cells_per_scan.tolist()):
        if i > start and (i - start >= chunk_scans or total + n > MAX_CELLS_PER_BATCH):
            out.append((start, i))
            start, total = i, 0
        total += n
    out.append((start, len(cells_per_scan)))
    return out


class _Tracer:
    """Holds the log-odds grid while batches of scans are traced into it."""

    def __init__(self, frame: tuple[float, float, int, int], cfg: MappingConfig):
        self.ox, self.oy, self.width, self.height = frame
        self.cfg = cfg
        self.cells = self.width * self.height
        self.log_odds = np.zeros(self.cells, dtype=np.float64)
        self.observed = np.zeros(self.cells, dtype=bool)

    def grid_coords(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous grid coordinates (u = column, v = row direction) of map-frame points."""
        return (x - self.ox) / self.cfg.resolution, (y - self.oy) / self.cfg.resolution

    def flat(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        return np.clip(row, 0, self.height - 1) * self.width + np.clip(col, 0, self.width - 1)

    def trace(self, poses: np.ndarray, valid: np.ndarray, ex: np.ndarray, ey: np.ndarray) -> None:
        """Update the grid with one batch of scans: poses (n, 3); valid, ex, ey (n, B)."""
        scan, beam = np.nonzero(valid)
        u0, v0 = self.grid_coords(poses[scan, 0], poses[scan, 1])
        u1, v1 = self.grid_coords(ex[scan, beam], ey[scan, beam])
        c0, r0 = np.floor(u0).astype(np.int64), np.floor(v0).astype(np.int64)
        c1, r1 = np.floor(u1).astype(np.int64), np.floor(v1).astype(np.int64)
        # Cells a beam passes through: its start cell and the cell entered at each grid-line crossing.
        cols_x, rows_x, bx = _entered(c0, c1, u0, u1 - u0, v0, v1 - v0)  # crossing vertical lines
        rows_y, cols_y, by = _entered(r0, r1, v0, v1 - v0, u0, u1 - u0)  # crossing horizontal lines
        passed = np.concatenate([self.flat(r0, c0), self.flat(rows_x, cols_x), self.flat(rows_y, cols_y)])
        passed_scan = np.concatenate([scan, scan[bx], scan[by]])
        # Key = scan * cells + cell: one sort de-duplicates per scan and orders the updates by scan.
        miss = _unique(passed_scan * self.cells + passed)
        hit = _unique(scan * self.cells + self.flat(r1, c1))
        miss = miss[~np.isin(miss, hit, assume_unique=True)]  # the endpoint cells, and any hit, are not misses
        bounds = np.arange(len(poses) + 1) * self.cells
        hb, mb = np.searchsorted(hit, bounds), np.searchsorted(miss, bounds)
        lo, hi = -self.cfg.log_odds_clamp, self.cfg.log_odds_clamp
        L = self.log_odds
        for j in range(len(poses)):  # per scan (not per beam): the clamp must follow each scan
            m = miss[mb[j] : mb[j + 1]] - j * self.cells
            h = hit[hb[j] : hb[j + 1]] - j * self.cells
            L[m] = np.maximum(L[m] - self.cfg.log_odds_miss, lo)
            L[h] = np.minimum(L[h] + self.cfg.log_odds_hit, hi)
            self.observed[m] = True
            self.observed[h] = True

    def to_map(self) -> OccupancyMap:
        p = 1.0 / (1.0 + np.exp(-self.log_odds))
        grid = np.full(self.cells, UNKNOWN, dtype=np.int8)
        grid[self.observed & (p < self.cfg.free_thresh)] = FREE
        grid[self.observed & (p > self.cfg.occupied_thresh)] = OCCUPIED
        return OccupancyMap(
            grid=grid.reshape(self.height, self.width),
            resolution=float(self.cfg.resolution),
            origin_x=self.ox,
            origin_y=self.oy,
        )


def _entered(
    a0: np.ndarray, a1: np.ndarray, a_start: np.ndarray, da: np.ndarray, b_start: np.ndarray, db: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells entered where segments cross the grid lines of one axis (exact traversal, Amanatides & Woo).

    Per segment: `a0`, `a1` are the start and end cell indices along axis a, `a_start` + t `da` (t in [0, 1])
    its continuous coordinate along a, `b_start` + t `db` along the other axis. Returns (a index, b index,
    segment index) of every cell entered. Crossing lines in any order gives the same cells, so no sort
    is needed: the k-th line crossed is found from its index alone, the other coordinate from where the
    segment meets it.
    """
    n = np.abs(a1 - a0)
    which = np.repeat(np.arange(n.size), n)
    k = np.arange(which.size) - np.repeat(np.cumsum(n) - n, n)  # 0 .. n-1 within each segment
    forward = (a1 > a0)[which]
    line = a0[which] + np.where(forward, k + 1, -k)  # grid line crossed (its coordinate along a)
    t = (line - a_start[which]) / da[which]  # da != 0 wherever a line is crossed
    a_cell = np.where(forward, line, line - 1)
    b_cell = np.floor(b_start[which] + t * db[which]).astype(np.int64)
    return a_cell, b_cell, which


def _unique(keys: np.ndarray) -> np.ndarray:
    """Sorted unique int64 keys; cheaper than np.unique here (numpy >= 2.3 hashes: ~8x slower on these)."""
    if keys.size == 0:
        return keys
    keys = np.sort(keys)
    return keys[np.concatenate(([True], keys[1:] != keys[:-1]))]


def build_occupancy_map(
    poses: np.ndarray,
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_max: float,
    cfg: MappingConfig | None = None,
    *,
    frame: tuple[float, float, int, int] | None = None,
    progress: bool = True,
) -> OccupancyMap:
    """Map from scans taken at known map_from_laser `poses` (N, 3); `ranges` (N, B), >= range_max = no return.

    The grid covers the poses and every used endpoint plus `cfg.margin_m`; origin = lower-left corner. With
    `frame` = (origin_x, origin_y, width, height) the grid is that one (an existing map's, to patch it), and
    beams from or to a point outside it are not used.
    """
    from pipeline.progress import progress_bar

    cfg = cfg or MappingConfig()
    poses = np.asarray(poses, dtype=np.float64)
    ranges = np.asarray(ranges)
    if poses.ndim != 2 or poses.shape[1] != 3 or ranges.ndim != 2 or len(ranges) != len(poses) or len(poses) == 0:
        raise ValueError(f"need poses (N, 3) and ranges (N, B) with N > 0, got {poses.shape} and {ranges.shape}")
    if not np.isfinite(poses).all():
        raise ValueError(f"poses must be finite; row {int(np.nonzero(~np.isfinite(poses).all(axis=1))[0][0])} is not")
    valid = valid_returns(ranges, range_max, cfg.max_range_m)
    ex, ey = beam_endpoints(poses, ranges, angle_min, angle_increment)
    if frame is None:
        frame = _grid_frame(np.concatenate([poses[:, 0], ex[valid]]), np.concatenate([poses[:, 1], ey[valid]]), cfg)
    else:
        check_map_size(frame[2] * cfg.resolution, frame[3] * cfg.resolution, cfg.resolution)
        valid = valid & _inside(frame, cfg.resolution, ex, ey) & _inside(frame, cfg.resolution, poses[:, :1],
                                                                         poses[:, 1:2])
    tracer = _Tracer(frame, cfg)
    # Cells each scan's beams cross (|d col| + |d row| + 1 per beam): the batch size in memory.
    crossings = (np.abs(ex - poses[:, 0:1]) + np.abs(ey - poses[:, 1:2])) / cfg.resolution + 2
    per_scan = np.where(valid, crossings, 0).sum(axis=1).astype(np.int64)
    with progress_bar(total=len(poses), unit="scan", desc="mapping", enabled=progress, leave=False) as bar:
        for a, b in _batches(per_scan, cfg.chunk_scans):
            tracer.trace(poses[a:b], valid[a:b], ex[a:b], ey[a:b])
            bar.update(b - a)
    return tracer.to_map()


def endpoint_occupied_share(
    occ_map: OccupancyMap,
    poses: np.ndarray,
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_max: float,
    tolerance_cells: int = 0,
    *,
    max_range: float | None = None,
) -> float:
    """Share of valid scan endpoints that fall on an occupied cell (NaN if there are none).

    With `tolerance_cells` = k, any occupied cell in the (2k+1)^2 neighbourhood counts: k = 1 forgives
    the half-cell quantisation of a wall seen from different sides. Endpoints outside the map count as misses.
    """
    valid = valid_returns(ranges, range_max, max_range)
    if not valid.any():
        return float("nan")
    ex, ey = beam_endpoints(poses, ranges, angle_min, angle_increment)
    row, col = occ_map.world_to_cell(ex[valid], ey[valid])
    occ = _dilate(occ_map.occupied, int(tolerance_cells))
    inside = occ_map.contains(row, col)
    on = np.zeros(row.shape, dtype=bool)
    on[inside] = occ[row[inside], col[inside]]
    return float(on.mean())


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """Square (2k+1)^2 binary dilation with plain numpy shifts (k is small)."""
    if k <= 0:
        return mask
    h, w = mask.shape
    padded = np.pad(mask, k)
    out = np.zeros_like(mask)
    for dr in range(2 * k + 1):
        for dc in range(2 * k + 1):
            out |= padded[dr : dr + h, dc : dc + w]
    return out
