"""Where and how the reference site is captured: stops, mapping and query runs with odometry and kidnappings.

Stops sample the floor the robot can reach from the corridors every ~`spacing` metres with `clearance`
to anything that is not free (walls, furniture, unknown space), so captures are spread over rooms and
corridors alike. Runs drive routes (`pipeline.sitegen.routes`) through that space: mapping runs tour the
stops, query runs pass between them and look in headings the stops' views never had, and are kidnapped
(carried far away) a few times. Odometry is the motion the robot really made, perturbed with the
odometry motion model's noise (`pipeline.runtime.motion`, as `pipeline.io.odometry` does for logs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt, label
from scipy.sparse.csgraph import dijkstra

from pipeline.config import OdometryNoise
from pipeline.io.capture_runs import write_run
from pipeline.io.map_yaml import OccupancyMap
from pipeline.io.odometry import integrate_deltas, noise_alphas
from pipeline.io.site import Rig
from pipeline.runtime.motion import odometry_delta, sample_odometry_deltas, wrap_angle
from pipeline.sitegen.routes import RoutePlanner, clearance_field, plan_route, resample, smooth_headings
from pipeline.sitegen.scene import Scene

__all__ = ["SimRun", "Stop", "make_runs", "plan_route", "reachable_mask", "sample_stops", "write_capture_run"]

Stop = tuple[float, float, float]  # (x, y, base heading) map_from_base at a capture stop


def reachable_mask(scene: Scene, occ_map: OccupancyMap, clearance: float) -> np.ndarray:
    """Cells with `clearance` connected (4-neighbourhood) to a corridor; the largest region if there is none."""
    ok = clearance_field(occ_map) >= clearance
    labels, n = label(ok)
    if n == 0:
        return ok
    rows, cols = np.nonzero(ok)
    xs, ys = occ_map.cell_to_world(rows, cols)
    keep = np.zeros(n + 1, dtype=bool)
    for room in scene.rooms:
        if room.kind == "corridor":
            keep[np.unique(labels[rows, cols][room.rect.contains(xs, ys)])] = True
    keep[0] = False
    if not keep.any():
        keep[np.argmax(np.bincount(labels.ravel())[1:]) + 1] = True
    return keep[labels]


def sample_stops(
    scene: Scene,
    occ_map: OccupancyMap,
    spacing: float = 2.0,
    clearance: float = 0.45,
    jitter: float = 0.3,
    seed: int = 0,
    pass_clearance: float = 0.3,
) -> list[Stop]:
    """Capture stops on a randomly offset, jittered grid of `spacing` over the free space reachable from
    the corridors through gaps of `pass_clearance` (a robot's radius: doorways are narrower than
    2 * `clearance`), each with `clearance`. Grid points that miss snap to the nearest valid cell within
    0.35 spacing; points closer than 0.6 spacing to a kept one are dropped; every room with a valid cell
    0.6 spacing away from all stops but no stop gets one (its best-cleared such cell), so small rooms the
    grid missed are captured too. Base headings are uniform. Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    res = occ_map.resolution
    valid = reachable_mask(scene, occ_map, pass_clearance) & (clearance_field(occ_map) >= clearance)
    if not valid.any():
        return []
    dist, (near_r, near_c) = distance_transform_edt(~valid, return_indices=True)
    b = scene.bounds
    off = rng.uniform(0.0, spacing, 2)
    gx, gy = np.meshgrid(np.arange(b.x0 + off[0], b.x1, spacing), np.arange(b.y0 + off[1], b.y1, spacing))
    px = gx.ravel() + rng.uniform(-jitter, jitter, gx.size)
    py = gy.ravel() + rng.uniform(-jitter, jitter, gx.size)
    row, col = occ_map.world_to_cell(px, py)
    row, col = np.clip(row, 0, occ_map.height - 1), np.clip(col, 0, occ_map.width - 1)
    ok = dist[row, col] * res <= 0.35 * spacing
    snapped = ~valid[row, col] & ok
    sx, sy = occ_map.cell_to_world(near_r[row, col], near_c[row, col])
    px, py = np.where(snapped, sx, px)[ok], np.where(snapped, sy, py)[ok]
    kept: list[tuple[float, float]] = []
    for x, y in zip(px, py, strict=True):
        if all(math.hypot(x - kx, y - ky) >= 0.6 * spacing for kx, ky in kept):
            kept.append((float(x), float(y)))
    rows, cols = np.nonzero(valid)
    cx, cy = occ_map.cell_to_world(rows, cols)
    clear = clearance_field(occ_map)[rows, cols]
    for room in scene.rooms:
        if any(room.rect.contains(x, y) for x, y in kept):
            continue
        inside = room.rect.contains(cx, cy)
        if not inside.any():
            continue
        rx, ry, rc = cx[inside], cy[inside], clear[inside]
        if kept:
            pts = np.array(kept)
            apart = np.min(np.hypot(rx[:, None] - pts[None, :, 0], ry[:, None] - pts[None, :, 1]), axis=1)
            rx, ry, rc = rx[apart >= 0.6 * spacing], ry[apart >= 0.6 * spacing], rc[apart >= 0.6 * spacing]
        if rc.size:  # else the room's reachable corner is already covered by a stop next door
            best = int(np.argmax(rc))
            kept.append((float(rx[best]), float(ry[best])))
    headings = rng.uniform(-math.pi, math.pi, len(kept))
    return [(x, y, float(h)) for (x, y), h in zip(kept, headings, strict=True)]


#: Headings of the capture rig's views relative to the base (site.yaml's default 6-view rig), radians.
RIG_OFFSETS = tuple(math.radians(v) for v in Rig().yaw_offsets_deg)


@dataclass
class SimRun:
    """One simulated run: ground truth map_from_base, odometry odom_from_base, per-step kidnap flags."""

    name: str
    kind: str  # "mapping" or "query"
    t: np.ndarray  # (N,) seconds
    gt: np.ndarray  # (N, 3)
    odom: np.ndarray  # (N, 3)
    kidnapped: np.ndarray  # (N,) bool: the robot was carried away before this step


class _Driver:
    """Drives routes between waypoints on one planner; everything random comes from one generator."""

    def __init__(self, planner: RoutePlanner, stops: np.ndarray, step: float, rng: np.random.Generator):
        self.planner, self.step, self.rng = planner, step, rng
        w = planner.shape[1]
        nodes = np.array([planner.node(x, y) for x, y in stops[:, :2]])
        comp = planner.labels[nodes // w, nodes % w]
        self.main = int(np.bincount(comp).argmax())  # the stops' connected part of the floor
        self.stops = stops[comp == self.main]
        if len(self.stops) < 2:
            raise ValueError("need at least two stops connected with the route clearance")

    def valid(self, x: float, y: float) -> bool:
        """Driveable and in the stops' part of the floor."""
        return self.planner.is_clear(x, y) and self.planner.connected((x, y), tuple(self.stops[0, :2]))

    def near(self, x: float, y: float, lo: float, hi: float) -> tuple[float, float]:
        """A valid point lo..hi metres from (x, y) in a random direction, or (x, y) itself."""
        for _ in range(12):
            d, a = self.rng.uniform(lo, hi), self.rng.uniform(-math.pi, math.pi)
            if self.valid(x + d * math.cos(a), y + d * math.sin(a)):
                return x + d * math.cos(a), y + d * math.sin(a)
        return float(x), float(y)

    def drive(self, start: tuple[float, float], waypoints, n_steps: int, wobble: float) -> np.ndarray:
        """(n_steps, 3) poses from `start` through waypoints drawn from the iterator until long enough."""
        parts, total, cur = [np.array([start], dtype=float)], 0.0, start
        for _ in range(10 * n_steps + 10):
            if total >= (n_steps + 1) * self.step:
                break
            nxt = next(waypoints)
            leg = self.planner.leg(cur, nxt)
            parts.append(leg[1:])
            total += float(np.hypot(*np.diff(leg, axis=0).T).sum())
            cur = nxt
        if total < (n_steps - 1) * self.step:
            raise ValueError(f"could not route {n_steps} steps of {self.step} m from {start} (too few stops apart?)")
        xy, direction = resample(np.vstack(parts), self.step)
        return np.column_stack([xy, smooth_headings(direction, wobble, self.rng)])[:n_steps]

    def tour(self, first: int, reverse: bool = False):
        """Stops in greedy nearest-neighbour order by driving distance from `first` (so a tour finishes a
        room or a corridor before it moves on, instead of hopping through walls to the next room), cyclically,
        each 0-0.3 m off the stop; `reverse`: the same tour driven the other way round."""
        nodes = np.array([self.planner.node(x, y) for x, y in self.stops[:, :2]])
        left, order = np.ones(len(nodes), dtype=bool), [first]
        left[first] = False
        while left.any():
            # The nearest stop left is usually a few metres away: a bounded search finds it exactly, and
            # the floor-wide one (every planning cell, for each of ~1000 stops on the paper preset) runs
            # only when none is that close.
            for limit in (12.0, 48.0, np.inf):
                found = dijkstra(self.planner.graph, indices=nodes[order[-1]], limit=limit)[nodes]
                d = np.where(left, found, np.inf)
                if np.isfinite(d).any():
                    break
            order.append(int(np.argmin(d)))
            left[order[-1]] = False
        if reverse:
            order = [order[0], *order[:0:-1]]
        while True:
            for j in order:
                yield self.near(*self.stops[j, :2], 0.0, 0.3)

    def wander(self, start: tuple[float, float]):
        """Between stops: random walk over near stops, via the midpoint of each hop (or a point 0.6-1 m
        from the next stop where the midpoint is not driveable), never at the stops themselves."""
        xy = self.stops[:, :2]
        cur, recent = int(np.argmin(np.hypot(*(xy - np.asarray(start)).T))), []
        while True:
            dist = np.hypot(*(xy - xy[cur]).T)
            cand = [j for j in np.argsort(dist)[1:7] if j not in recent] or list(np.argsort(dist)[1:3])
            nxt = int(self.rng.choice(cand))
            mx, my = 0.5 * (xy[cur] + xy[nxt]) + self.rng.normal(0.0, 0.2, 2)
            yield (float(mx), float(my)) if self.valid(mx, my) else self.near(*xy[nxt], 0.6, 1.0)
            recent, cur = [*recent[-3:], cur], nxt


def unseen_headings(poses: np.ndarray, stops: np.ndarray, seen_offsets, max_turn: float = math.pi / 6) -> np.ndarray:
    """Headings within `max_turn` of `poses`' own that stay as far as possible from every view heading
    (stop heading + `seen_offsets`) of the nearest stop; turned smoothly over a few steps. Radians."""
    near = np.argmin(np.hypot(poses[:, None, 0] - stops[None, :, 0], poses[:, None, 1] - stops[None, :, 1]), axis=1)
    seen = stops[near, 2][:, None] + np.asarray(seen_offsets)[None, :]  # (N, V)
    turns = np.linspace(-max_turn, max_turn, 13)
    cand = poses[:, 2:3] + turns[None, :]  # (N, T)
    gap = np.abs(wrap_angle(cand[:, :, None] - seen[:, None, :])).min(axis=2) - 1e-3 * np.abs(turns)[None, :]
    turn = turns[np.argmax(gap, axis=1)]
    if len(turn) > 3:
        turn = np.convolve(np.pad(turn, 1, mode="edge"), np.ones(3) / 3, mode="valid")
    return wrap_angle(poses[:, 2] + turn)


def make_runs(
    scene: Scene,
    occ_map: OccupancyMap,
    stops: list[Stop],
    n_mapping: int,
    n_query: int,
    steps_per_run: int,
    step: float = 0.4,
    kidnaps_per_query_run: int = 1,
    seed: int = 0,
    *,
    mapping_steps: int | None = None,
    noise: OdometryNoise | None = None,
    dt: float = 0.5,
    clearance: float = 0.3,
    wobble: float = 0.03,
    seen_offsets=RIG_OFFSETS,
    kidnap_min_distance: float = 5.0,
    planner: RoutePlanner | None = None,
) -> list[SimRun]:
    """Mapping runs (tours of the stops, `mapping_steps` long, default `steps_per_run`; in pairs, each way
    round from the same stop) and query runs (between
    stops, in unseen headings, kidnapped `kidnaps_per_query_run` times to a random driveable place more
    than `kidnap_min_distance` away). At a kidnap the ground truth jumps but the odometry only sees the
    robot being lifted and set down (a few cm and degrees); the step after the jump is flagged.
    `scene` is not needed beyond the map today; it is kept for runs that depend on rooms."""
    del scene
    rng = np.random.default_rng(seed)
    noise = noise or OdometryNoise()
    planner = planner or RoutePlanner(occ_map, clearance)
    drv = _Driver(planner, np.asarray(stops, dtype=np.float64).reshape(-1, 3), step, rng)
    runs = []
    # The mapping runs draw from their own stream, so the query runs do not change with how long or how
    # many the mapping runs are.
    query_rng, drv.rng = rng, np.random.default_rng([seed, 1])
    for j in range(n_mapping):
        # Runs in pairs: one tour each way round from the same stop, so the database has sequences of each
        # corridor in both directions of travel; pairs start at different points of the floor.
        first = int((j // 2) * len(drv.stops) / max((n_mapping + 1) // 2, 1))
        gt = drv.drive(tuple(drv.stops[first, :2]), drv.tour(first, reverse=j % 2 == 1), mapping_steps or steps_per_run,
                       wobble)
        runs.append(_finish(f"mapping_{j:02d}", "mapping", gt, np.zeros(len(gt), bool), noise, dt, drv.rng))
    rng = drv.rng = query_rng
    for j in range(n_query):
        cuts = _kidnap_steps(steps_per_run, kidnaps_per_query_run, rng)
        start = drv.near(*drv.stops[rng.integers(len(drv.stops)), :2], 0.6, 1.0)
        parts, kidnapped = [], np.zeros(steps_per_run, bool)
        for a, b in zip([0, *cuts], [*cuts, steps_per_run], strict=True):
            if a > 0:
                start = _landing(planner, drv.main, parts[-1][-1, :2], kidnap_min_distance, rng)
                kidnapped[a] = True
            seg = drv.drive(start, drv.wander(start), b - a, wobble)
            seg[:, 2] = unseen_headings(seg, drv.stops, seen_offsets)
            parts.append(seg)
        runs.append(_finish(f"query_{j:02d}", "query", np.vstack(parts), kidnapped, noise, dt, rng))
    return runs


def _kidnap_steps(n: int, k: int, rng: np.random.Generator) -> list[int]:
    """k steps spread over the run (one per equal bin of [n/5, n - 3)), at least half a bin (and 3 steps)
    apart, so that each kidnapping leaves room to measure its recovery before the next."""
    if k <= 0 or n < 10:
        return []
    edges = np.linspace(n // 5, n - 3, k + 1).astype(int)
    gap = max(3, int(edges[1] - edges[0]) // 2)
    steps, prev = [], -gap
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        lo = min(max(lo, prev + gap), hi - 3)
        prev = int(rng.integers(lo, max(lo + 1, hi - 2)))
        steps.append(prev)
    return sorted({s for s in steps if s > 0})


def _landing(planner: RoutePlanner, main: int, here: np.ndarray, min_dist: float, rng) -> tuple[float, float]:
    """A random driveable planning cell of the main region more than `min_dist` from `here`."""
    rows, cols = np.nonzero(planner.labels == main)
    xy = planner.node_xy(rows * planner.shape[1] + cols)
    far = np.nonzero(np.hypot(*(xy - here).T) > min_dist)[0]
    if far.size == 0:
        raise ValueError(f"no driveable place more than {min_dist} m away from {here} to kidnap the robot to")
    return tuple(float(v) for v in xy[rng.choice(far)])


def _finish(name: str, kind: str, gt: np.ndarray, kidnapped: np.ndarray, noise, dt: float, rng) -> SimRun:
    """Odometry for a run: the motion actually made, with the motion model's noise, integrated from 0."""
    rot1, trans, rot2 = odometry_delta(gt[:-1], gt[1:])
    carried = kidnapped[1:]  # the transition into a flagged step is the teleport
    n = int(carried.sum())
    rot1, trans, rot2 = rot1.copy(), trans.copy(), rot2.copy()
    rot1[carried], trans[carried], rot2[carried] = 0.0, np.abs(rng.normal(0.0, 0.02, n)), rng.normal(0.0, 0.03, n)
    odom = integrate_deltas(*sample_odometry_deltas(rot1, trans, rot2, noise_alphas(noise), rng))
    return SimRun(name, kind, dt * np.arange(len(gt)), gt, odom, kidnapped.copy())


def write_capture_run(run_dir: Path, run: SimRun, ranges: np.ndarray, image_names=None) -> Path:
    """`trajectory.csv` + `scans.npy` of a run in the capture-directory format (`pipeline.io.capture_runs`),
    each file written atomically. `image_names`: site-relative path or None per step."""
    run_dir = Path(run_dir)
    n = len(run.t)
    ranges = np.asarray(ranges, dtype=np.float32)
    images = list(image_names) if image_names is not None else [None] * n
    if ranges.ndim != 2 or ranges.shape[0] != n or len(images) != n:
        raise ValueError(f"{n} steps need ranges [{n}, beams] and {n} image names, got {ranges.shape}, {len(images)}")
    write_run(run_dir, run.t, run.odom, run.gt, ranges, images, run.kidnapped)
    return run_dir
