"""The reference site's 2D laser: the map a mapping team would have, the world the laser sees, and scans.

`rasterise_map` draws the scene at the laser's height: walls minus their open doorways (closed doors
and windows stay solid at that height), laser-blocking objects' footprints; free inside the building,
unknown outside it and in `scene.closed` cores (nobody mapped them). The laser world
(`laser_world_grid`) is the same plus what the map does not know: people standing around and moved
furniture, so localization is tested against unmapped obstacles as on a real floor. People who walk
during a run are not rasterised per step: `LaserScanner` intersects their discs analytically.

`LaserScanner` sphere-traces every beam on the Euclidean distance field of the world (one
`distance_transform_edt` per world): a ray advances by the distance to the nearest occupied cell minus
the worst-case offset of a point inside its cell (sqrt(2) cells), so it never enters an occupied cell;
where that safe distance drops under one cell it steps exactly, cell boundary by cell boundary (DDA), so
grazing rays are exact too, and a hit is the boundary where the ray enters the first occupied cell. All
beams (of several poses at once) advance together in numpy, rays leaving the active set as they finish.
Ranges follow the capture contract: float32, a no-return is exactly `range_max`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from pipeline.runtime.kernels import safe_steps
from pipeline.sitegen.scene import Rect, Scene, Wall

#: Border around the building's outer wall rectangle, so the outer walls' outside halves fit in the grid.
MARGIN_M = 1.0
#: A hit is reported this far past the boundary of the occupied cell (at most half way through the cell),
#: so the endpoint's cell is that cell (exactly on the boundary, rounding could put it into the free cell).
HIT_INSET_M = 1e-4
#: Rotated rectangle (cx, cy, yaw, width along the local x, depth along the local y), map frame.
RectPose = tuple[float, float, float, float, float]


def wall_pieces(wall: Wall) -> list[RectPose]:
    """The solid stretches of a wall as rotated rectangles: everything but its `doorway` openings."""
    length = wall.length
    gaps = sorted((max(0.0, float(o.start)), min(length, float(o.end))) for o in wall.openings if o.kind == "doorway")
    dx, dy = wall.direction
    yaw = math.atan2(dy, dx)
    pieces, at = [], 0.0
    for a, b in [*gaps, (length, length)]:
        if a > at + 1e-9:
            mid = 0.5 * (at + a)
            pieces.append((wall.x0 + dx * mid, wall.y0 + dy * mid, yaw, a - at, wall.thickness))
        at = max(at, b)
    return pieces


def _cell_centres(occ: OccupancyMap, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
    xs = occ.origin_x + (np.arange(c0, c1) + 0.5) * occ.resolution
    ys = occ.origin_y + (np.arange(r0, r1) + 0.5) * occ.resolution
    return xs[None, :], ys[:, None]


def _bbox(occ: OccupancyMap, x0: float, y0: float, x1: float, y1: float) -> tuple[int, int, int, int]:
    """Row/column slice bounds of the cells whose centres may lie in [x0, x1] x [y0, y1], clipped to the grid."""
    res = occ.resolution
    c0 = max(0, int(math.floor((x0 - occ.origin_x) / res - 0.5)))
    c1 = min(occ.width, int(math.ceil((x1 - occ.origin_x) / res + 0.5)))
    r0 = max(0, int(math.floor((y0 - occ.origin_y) / res - 0.5)))
    r1 = min(occ.height, int(math.ceil((y1 - occ.origin_y) / res + 0.5)))
    return r0, r1, c0, c1


def fill_rects(mask: np.ndarray, frame: OccupancyMap, rects: Iterable[RectPose]) -> None:
    """Set the cells whose centres lie in rotated rectangles (in place), testing only each bounding box.

    Half-sizes are raised to half a cell's extent across them, so a wall thinner than a cell (or a thin
    door leaf) still forms an unbroken barrier instead of a dotted line the laser slips through.
    """
    res = frame.resolution
    for cx, cy, yaw, width, depth in rects:
        c, s = math.cos(yaw), math.sin(yaw)
        floor_half = 0.5 * res * (abs(c) + abs(s))
        hx, hy = max(0.5 * width, floor_half), max(0.5 * depth, floor_half)
        ex, ey = abs(c) * hx + abs(s) * hy, abs(s) * hx + abs(c) * hy
        r0, r1, c0, c1 = _bbox(frame, cx - ex, cy - ey, cx + ex, cy + ey)
        if r0 >= r1 or c0 >= c1:
            continue
        xs, ys = _cell_centres(frame, r0, r1, c0, c1)
        u = c * (xs - cx) + s * (ys - cy)
        v = -s * (xs - cx) + c * (ys - cy)
        mask[r0:r1, c0:c1] |= (np.abs(u) <= hx + 1e-9) & (np.abs(v) <= hy + 1e-9)


def fill_discs(mask: np.ndarray, frame: OccupancyMap, discs: Iterable[tuple[float, float, float]]) -> None:
    """Set the cells whose centres lie in discs (x, y, radius), in place."""
    for x, y, r in discs:
        r = max(float(r), 0.5 * frame.resolution)
        r0, r1, c0, c1 = _bbox(frame, x - r, y - r, x + r, y + r)
        if r0 < r1 and c0 < c1:
            xs, ys = _cell_centres(frame, r0, r1, c0, c1)
            mask[r0:r1, c0:c1] |= (xs - x) ** 2 + (ys - y) ** 2 <= r * r


def _rect_mask(frame: OccupancyMap, rect: Rect) -> tuple[slice, slice, np.ndarray]:
    r0, r1, c0, c1 = _bbox(frame, rect.x0, rect.y0, rect.x1, rect.y1)
    xs, ys = _cell_centres(frame, r0, r1, c0, c1)
    return slice(r0, r1), slice(c0, c1), rect.contains(xs, ys)


def _empty_frame(scene: Scene, resolution: float) -> OccupancyMap:
    b = scene.bounds
    width = int(math.ceil(round((b.w + 2 * MARGIN_M) / resolution, 6)))
    height = int(math.ceil(round((b.h + 2 * MARGIN_M) / resolution, 6)))
    grid = np.full((height, width), UNKNOWN, dtype=np.int8)
    return OccupancyMap(grid, float(resolution), b.x0 - MARGIN_M, b.y0 - MARGIN_M)


def _object_rects(scene: Scene, skip_ids: set[int], skip_closed: bool) -> list[RectPose]:
    out = []
    for o in scene.objects:
        if not o.blocks_laser or o.instance_id in skip_ids:
            continue
        if skip_closed and any(r.contains(o.x, o.y) for r in scene.closed):
            continue
        # The object's yaw is the heading of its front (model -y), so its width axis points at yaw + pi/2.
        out.append((o.x, o.y, o.yaw + math.pi / 2, o.size[0], o.size[1]))
    return out


def _rasterise(scene: Scene, resolution: float, skip_ids: set[int], skip_closed: bool) -> OccupancyMap:
    occ = _empty_frame(scene, resolution)
    xs, ys = _cell_centres(occ, 0, occ.height, 0, occ.width)
    occ.grid[scene.bounds.contains(xs, ys)] = FREE
    for rect in scene.closed:
        rows, cols, inside = _rect_mask(occ, rect)
        occ.grid[rows, cols][inside] = UNKNOWN
    solid = np.zeros(occ.grid.shape, dtype=bool)
    fill_rects(solid, occ, [p for wall in scene.walls for p in wall_pieces(wall)])
    fill_rects(solid, occ, _object_rects(scene, skip_ids, skip_closed))
    occ.grid[solid] = OCCUPIED
    return occ


def rasterise_map(scene: Scene, resolution: float = 0.05) -> OccupancyMap:
    """The occupancy map a mapping team would hand over (see the module docstring); origin at the
    bounds' lower-left corner minus `MARGIN_M`. Objects inside closed cores are not in it (never seen)."""
    return _rasterise(scene, resolution, set(), skip_closed=True)


def laser_world_grid(
    scene: Scene,
    resolution: float = 0.05,
    extra_discs: Sequence[tuple[float, float, float]] = (),
    extra_rects: Sequence[RectPose] = (),
    removed_ids: Iterable[int] = (),
) -> OccupancyMap:
    """What the laser actually sees: the map's geometry (and whatever is inside closed cores), minus
    the objects `removed_ids` that were moved away, plus unmapped obstacles: discs (x, y, r) such as
    people standing still, rotated rectangles such as moved chairs at their new places."""
    occ = _rasterise(scene, resolution, set(removed_ids), skip_closed=False)
    solid = np.zeros(occ.grid.shape, dtype=bool)
    fill_discs(solid, occ, extra_discs)
    fill_rects(solid, occ, extra_rects)
    occ.grid[solid] = OCCUPIED
    return occ


def displace_furniture(
    scene: Scene,
    occ_map: OccupancyMap,
    share: float,
    seed: int,
    kinds: tuple[str, ...] = ("chair",),
    keep_clear: np.ndarray | None = None,
    keep_radius: float = 0.6,
) -> tuple[list[RectPose], list[int]]:
    """Move a `share` of the laser-blocking objects of `kinds` by 0.3-1 m (new yaw jittered): returns
    their new footprints and the ids to remove from the world. A new place must be free in the map
    and, if `keep_clear` (M, 2) points are given (the runs' positions), not where the robot drives."""
    rng = np.random.default_rng(seed)
    movable = [o for o in scene.objects if o.kind in kinds and o.blocks_laser]
    n = int(round(share * len(movable)))
    picked = [movable[i] for i in sorted(rng.choice(len(movable), size=n, replace=False))] if n else []
    rects, removed = [], []
    for o in picked:
        reach = 0.5 * math.hypot(o.size[0], o.size[1])
        for _ in range(20):
            dist, ang = rng.uniform(0.3, 1.0), rng.uniform(-math.pi, math.pi)
            x, y = o.x + dist * math.cos(ang), o.y + dist * math.sin(ang)
            corners = np.array([[x + sx * reach, y + sy * reach] for sx in (-1, 0, 1) for sy in (-1, 0, 1)])
            if np.any(occ_map.value_at(corners[:, 0], corners[:, 1]) != FREE):
                continue
            if keep_clear is not None and len(keep_clear):
                if np.min(np.hypot(keep_clear[:, 0] - x, keep_clear[:, 1] - y)) < keep_radius + reach:
                    continue
            rects.append((x, y, o.yaw + math.pi / 2 + rng.normal(0.0, 0.3), o.size[0], o.size[1]))
            removed.append(o.instance_id)
            break
    return rects, removed


def walking_people(
    free_mask: np.ndarray,
    frame: OccupancyMap,
    n_people: int,
    steps: int,
    seed: int,
    dt: float = 0.5,
    speed: float = 0.8,
    robot_xy: np.ndarray | None = None,
) -> np.ndarray:
    """Discs (steps, n_people, 3) of people walking straight at `speed`, turning where the next step
    would leave `free_mask` (cells where a person fits) or come within 0.7 m of the robot at that step."""
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(free_mask)
    out = np.zeros((steps, n_people, 3))
    if n_people == 0 or rows.size == 0:
        return out
    pick = rng.choice(rows.size, size=n_people)
    x, y = frame.cell_to_world(rows[pick], cols[pick])
    heading = rng.uniform(-math.pi, math.pi, n_people)
    radius = rng.uniform(0.2, 0.3, n_people)
    for k in range(steps):
        out[k, :, 0], out[k, :, 1], out[k, :, 2] = x, y, radius
        nx, ny = x + speed * dt * np.cos(heading), y + speed * dt * np.sin(heading)
        r, c = frame.world_to_cell(nx, ny)
        ok = frame.contains(r, c)
        ok[ok] = free_mask[r[ok], c[ok]]
        if robot_xy is not None and k + 1 < len(robot_xy):
            ok &= np.hypot(nx - robot_xy[k + 1, 0], ny - robot_xy[k + 1, 1]) > 0.7
        x, y = np.where(ok, nx, x), np.where(ok, ny, y)
        heading = np.where(ok, heading + rng.normal(0.0, 0.1, n_people), rng.uniform(-math.pi, math.pi, n_people))
    return out


def laser_poses(map_from_base: np.ndarray, base_from_laser: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """map_from_laser (N, 3) = map_from_base * base_from_laser (the runtime filter's own transform)."""
    from pipeline.runtime.sensor import laser_poses as compose

    return np.array(compose(np.asarray(map_from_base, dtype=np.float64), tuple(base_from_laser)), dtype=np.float64)


class LaserScanner:
    """A simulated planar laser on an occupancy world (only its occupied cells matter; see module docstring).

    Beam i points at angle_min + i * fov / (beams - 1) in the laser frame (angle_min = -fov / 2 unless
    given): evenly from angle_min to angle_max inclusive, as site.yaml's `laser` section. The constructor
    takes degrees as the site presets do; everything after it (poses, `angles`, `angle_min`,
    `angle_increment`) is in radians. Noise: Gaussian range noise `noise_sigma` (m) on returns, kept
    below `range_max`, and a `dropout` share of beams lost to range_max (glass, black surfaces).
    `range_max` may exceed 30 m; a ray also ends where it leaves the grid (no return).
    """

    def __init__(
        self,
        world: OccupancyMap,
        beams: int = 1081,
        fov_deg: float = 270.0,
        range_max: float = 30.0,
        noise_sigma: float = 0.01,
        dropout: float = 0.01,
        seed: int = 0,
        angle_min_deg: float | None = None,
    ):
        if world.origin_yaw:
            raise ValueError("LaserScanner needs an axis-aligned grid (origin yaw 0)")
        if beams < 2:
            raise ValueError(f"a scan needs at least 2 beams, got {beams}")
        self.beams, self.fov, self.range_max = int(beams), math.radians(fov_deg), float(range_max)
        self.noise_sigma, self.dropout = float(noise_sigma), float(dropout)
        self.angle_min = -0.5 * self.fov if angle_min_deg is None else math.radians(angle_min_deg)
        self.angle_increment = self.fov / (self.beams - 1)
        self.angles = self.angle_min + self.angle_increment * np.arange(self.beams)
        self.rng = np.random.default_rng(seed)
        self.res = float(world.resolution)
        self.origin = (float(world.origin_x), float(world.origin_y))
        self.height, self.width = world.grid.shape
        occupied = world.occupied
        self._occupied = occupied.ravel()
        # Safe step in cells, the runtime ray caster's definition (see `kernels.safe_steps`).
        self._safe = safe_steps(occupied).ravel() if occupied.any() else None

    def cast(self, map_from_laser: np.ndarray, rng: np.random.Generator | None = None, discs=None, noisy=True):
        """Ranges float32 (beams,) from one pose (x, y, theta); `discs` (K, 3) = (x, y, r) moving people."""
        return self.cast_many(np.asarray(map_from_laser, dtype=np.float64)[None], rng, discs, noisy)[0]

    def cast_many(
        self,
        map_from_laser: np.ndarray,
        rng: np.random.Generator | None = None,
        discs: np.ndarray | None = None,
        noisy: bool = True,
    ) -> np.ndarray:
        """Ranges float32 (N, beams) from N poses at once; `discs` (K, 3) for all or (N, K, 3) per pose."""
        poses = np.asarray(map_from_laser, dtype=np.float64).reshape(-1, 3)
        world = poses[:, 2:3] + self.angles[None, :]
        dx, dy = np.cos(world), np.sin(world)
        ox = np.broadcast_to(poses[:, 0:1], dx.shape)
        oy = np.broadcast_to(poses[:, 1:2], dx.shape)
        r = self._trace(ox.ravel(), oy.ravel(), dx.ravel(), dy.ravel()).reshape(dx.shape)
        if discs is not None and len(discs):
            d = np.asarray(discs, dtype=np.float64)
            d = np.broadcast_to(d, (len(poses), *d.shape[-2:])) if d.ndim == 2 else d
            r = np.minimum(r, _disc_ranges(poses, dx, dy, d))
        if noisy:
            rng = self.rng if rng is None else rng
            hit = r < self.range_max
            r = np.where(hit, np.clip(r + rng.normal(0.0, self.noise_sigma, r.shape), 0.0, self.range_max - 1e-3), r)
            r = np.where(rng.random(r.shape) < self.dropout, self.range_max, r)
        return np.minimum(r, self.range_max).astype(np.float32)

    def _trace(self, x: np.ndarray, y: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """Exact first-hit distance (m) of rays, range_max where none within range_max or the grid."""
        out = np.full(x.shape, self.range_max)
        if self._safe is None:
            return out
        inv = 1.0 / self.res
        u, v = (x - self.origin[0]) * inv, (y - self.origin[1]) * inv  # positions in cell units
        w, h = self.width, self.height
        # An axis-parallel beam gets a 1e-12 component instead of 0 (drift < 1e-8 cells over the range),
        # so no 0 * inf appears in the boundary distances.
        dx, dy = np.where(dx == 0.0, 1e-12, dx), np.where(dy == 0.0, 1e-12, dy)
        idx_, idy_ = 1.0 / dx, 1.0 / dy
        # Parameter (in cells) where each ray leaves the grid box [0, w] x [0, h], capped at range_max.
        exit_u = np.where(dx > 0, (w - u) * idx_, -u * idx_)
        exit_v = np.where(dy > 0, (h - v) * idy_, -v * idy_)
        tmax = np.minimum(np.minimum(exit_u, exit_v), self.range_max * inv)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ids = np.nonzero(inside)[0]
        # One packed array per active ray, so dropping finished rays is a single fancy-index.
        state = np.stack([u, v, dx, dy, idx_, idy_, tmax, np.zeros_like(u), dx > 0, dy > 0])[:, ids]
        occupied, safe_cells, wmax, hmax = self._occupied, self._safe, w - 1, h - 1
        for _ in range(4 * int(self.range_max * inv) + 16):  # each pass crosses >= 1 boundary or 1 cell
            if ids.size == 0:
                break
            u, v, dx, dy, idx_, idy_, tmax, t, stepu, stepv = state
            pu, pv = u + t * dx, v + t * dy
            cu = np.minimum(pu.astype(np.intp), wmax)  # pu >= 0 inside the grid, so truncation is floor
            cv = np.minimum(pv.astype(np.intp), hmax)
            flat = cv * w + cu
            hit = occupied[flat]
            safe = safe_cells[flat]
            dda = np.minimum((cu + stepu - pu) * idx_, (cv + stepv - pv) * idy_)  # to the cell's exit
            if hit.any():  # the ray entered an occupied cell at t (t = 0: the laser is inside an obstacle)
                th = t[hit] * self.res
                inset = np.minimum(HIT_INSET_M, 0.5 * dda[hit] * self.res)  # stay inside a clipped corner
                out[ids[hit]] = np.where(th > 0, np.minimum(th + inset, self.range_max), 0.0)
            # Far from obstacles a sphere step; near them step just past the next cell boundary (exact DDA).
            t += np.where(safe >= 1.0, safe, dda + 1e-7)
            done = hit | (t >= tmax)
            if done.any():
                keep = ~done
                state, ids = state[:, keep], ids[keep]
        return out


def _disc_ranges(poses: np.ndarray, dx: np.ndarray, dy: np.ndarray, discs: np.ndarray) -> np.ndarray:
    """Distance (N, B) along each beam to the nearest disc (N, K, 3) in front of it, inf where none.

    A disc around the laser itself is ignored (a person cannot stand inside the robot)."""
    ox = poses[:, 0:1, None] - discs[:, None, :, 0]  # (N, 1, K) origin relative to each disc centre
    oy = poses[:, 1:2, None] - discs[:, None, :, 1]
    rr = discs[:, None, :, 2] ** 2
    b = ox * dx[:, :, None] + oy * dy[:, :, None]  # (N, B, K)
    c = ox**2 + oy**2 - rr
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (c > 0) & (t > 0), t, np.inf)
    return t.min(axis=2)
