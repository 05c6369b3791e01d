"""Routes through the free space of a reference site: shortest paths with clearance, driven like a robot.

Routes are shortest paths on an 8-connected grid graph of the free space with clearance
(scipy.sparse.csgraph's Dijkstra: a real library, no hand-written A*; scikit-image's MCP is not
installed), string-pulled to a polyline so they run straight wherever the free space allows, and
resampled at a fixed step with the heading along the path plus a small wobble, like a driven robot's
ground truth (map_from_base poses, radians).

Clearance of a cell = distance from its centre to the nearest non-free cell's centre minus half a cell,
the distance to that cell's near edge for axis-aligned neighbours (`clearance_field`). Unknown cells
count as obstacles: nobody drives into unmapped space.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt, label
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from pipeline.io.map_yaml import OccupancyMap


def clearance_field(occ_map: OccupancyMap) -> np.ndarray:
    """Metres from each free cell to the nearest non-free cell (<= 0 on non-free cells); see module docstring."""
    return distance_transform_edt(occ_map.free) * occ_map.resolution - 0.5 * occ_map.resolution


class RoutePlanner:
    """Shortest paths with clearance on one map: the graph is built once, each leg is one Dijkstra.

    The graph lives on cells of about `plan_resolution` (blocks of map cells, valid only if all of them
    have `clearance`), 8-connected without cutting corners; the path is then string-pulled against the
    map-resolution clearance mask, so it runs straight wherever the free space allows."""

    def __init__(self, occ_map: OccupancyMap, clearance: float = 0.3, plan_resolution: float = 0.1):
        self.occ_map, self.clearance = occ_map, float(clearance)
        self.fine = clearance_field(occ_map) >= clearance
        self.f = f = max(1, int(round(plan_resolution / occ_map.resolution)))
        h, w = occ_map.height // f, occ_map.width // f
        self.ok = ok = self.fine[: h * f, : w * f].reshape(h, f, w, f).all(axis=(1, 3))
        self.labels, _ = label(ok)
        _, (self.near_r, self.near_c) = distance_transform_edt(~ok, return_indices=True)
        ids = np.arange(h * w).reshape(h, w)
        edges = [
            (ok[:, :-1] & ok[:, 1:], ids[:, :-1], ids[:, 1:], 1.0),
            (ok[:-1] & ok[1:], ids[:-1], ids[1:], 1.0),
            (ok[:-1, :-1] & ok[1:, 1:] & ok[:-1, 1:] & ok[1:, :-1], ids[:-1, :-1], ids[1:, 1:], math.sqrt(2.0)),
            (ok[:-1, 1:] & ok[1:, :-1] & ok[:-1, :-1] & ok[1:, 1:], ids[:-1, 1:], ids[1:, :-1], math.sqrt(2.0)),
        ]
        a = np.concatenate([src[m] for m, src, _, _ in edges])
        b = np.concatenate([dst[m] for m, _, dst, _ in edges])
        cost = np.concatenate([np.full(int(m.sum()), c * f * occ_map.resolution) for m, _, _, c in edges])
        self.graph = coo_matrix((np.r_[cost, cost], (np.r_[a, b], np.r_[b, a])), shape=(h * w, h * w)).tocsr()
        self.shape = (h, w)

    def node(self, x: float, y: float) -> int:
        """Graph node of the valid planning cell nearest to a map-frame point."""
        row, col = self.occ_map.world_to_cell(x, y)
        h, w = self.shape
        r, c = min(max(int(row) // self.f, 0), h - 1), min(max(int(col) // self.f, 0), w - 1)
        return int(self.near_r[r, c]) * w + int(self.near_c[r, c])

    def node_xy(self, nodes: np.ndarray) -> np.ndarray:
        h, w = self.shape
        x, y = self.occ_map.cell_to_world(nodes // w * self.f + (self.f - 1) / 2, nodes % w * self.f + (self.f - 1) / 2)
        return np.stack([x, y], axis=1)

    def is_clear(self, x: float, y: float) -> bool:
        """Whether a map-frame point lies on a map cell with the planner's clearance."""
        row, col = self.occ_map.world_to_cell(x, y)
        return bool(self.occ_map.contains(row, col) and self.fine[row, col])

    def connected(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        w = self.shape[1]
        na, nb = self.node(*a), self.node(*b)
        return bool(self.labels[na // w, na % w] == self.labels[nb // w, nb % w])

    def leg(self, a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
        """Polyline (M, 2) from a to b: Dijkstra on the planning graph, then string-pulled."""
        for p in (a, b):
            if not self.is_clear(*p):
                raise ValueError(f"waypoint {p} is not in free space with {self.clearance} m clearance")
        src, dst = self.node(*a), self.node(*b)
        if not self.connected(a, b):
            raise ValueError(f"no path with {self.clearance} m clearance from {a} to {b}")
        limit = 3.0 * math.hypot(b[0] - a[0], b[1] - a[1]) + 10.0  # search a disc first, then everything
        for lim in (limit, np.inf):
            dist, pred = dijkstra(self.graph, indices=src, return_predecessors=True, limit=lim)
            if np.isfinite(dist[dst]):
                break
        nodes = [dst]
        while nodes[-1] != src:
            nodes.append(int(pred[nodes[-1]]))
        pts = np.vstack([np.asarray(a, float)[None], self.node_xy(np.array(nodes[::-1])), np.asarray(b, float)[None]])
        return self.pull(pts)

    def visible(self, p: np.ndarray, qs: np.ndarray) -> np.ndarray:
        """Whether each straight segment p -> qs[j] stays on cells with clearance (sampled every res/4)."""
        res = self.occ_map.resolution
        n = int(np.ceil(np.max(np.hypot(*(qs - p).T)) / (0.25 * res))) + 2
        s = np.linspace(0.0, 1.0, n)[None, :, None]
        pts = p[None, None, :] + s * (qs - p)[:, None, :]
        row, col = self.occ_map.world_to_cell(pts[..., 0], pts[..., 1])
        inside = self.occ_map.contains(row, col)
        ok = np.zeros(row.shape, dtype=bool)
        ok[inside] = self.fine[row[inside], col[inside]]
        return ok.all(axis=1)

    def pull(self, pts: np.ndarray, lookahead: int = 120) -> np.ndarray:
        """String pulling: from each kept point jump to the farthest later point in straight-line sight."""
        out, i = [pts[0]], 0
        while i < len(pts) - 1:
            cand = np.arange(i + 1, min(len(pts), i + 1 + lookahead))
            seen = self.visible(pts[i], pts[cand])
            i = int(cand[np.nonzero(seen)[0][-1]]) if seen.any() else i + 1
            out.append(pts[i])
        return np.array(out)


def resample(polyline: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) every `step` metres of arc length along a polyline, and the travel direction there."""
    seg = np.diff(polyline, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 1e-9
    seg, length, start = seg[keep], length[keep], polyline[:-1][keep]
    s = np.concatenate([[0.0], np.cumsum(length)])
    at = np.arange(0.0, s[-1] + 1e-9, step)
    k = np.clip(np.searchsorted(s, at, side="right") - 1, 0, len(length) - 1)
    frac = (at - s[k]) / length[k]
    xy = start[k] + frac[:, None] * seg[k]
    return xy, np.arctan2(seg[k, 1], seg[k, 0])


def smooth_headings(direction: np.ndarray, wobble: float, rng: np.random.Generator, window: int = 3) -> np.ndarray:
    """Travel directions averaged over `window` steps (turns spread over a few steps, as a robot turns),
    plus low-pass Gaussian wobble of std ~`wobble` rad; wrapped to [-pi, pi)."""
    n = len(direction)
    c, s = np.cos(direction), np.sin(direction)
    if n > window:
        kernel = np.ones(window) / window
        pad = window // 2
        c = np.convolve(np.pad(c, pad, mode="edge"), kernel, mode="valid")
        s = np.convolve(np.pad(s, pad, mode="edge"), kernel, mode="valid")
    noise = np.convolve(rng.normal(0.0, wobble * math.sqrt(5.0), n + 4), np.ones(5) / 5, mode="valid")
    return (np.arctan2(s, c) + noise + np.pi) % (2 * np.pi) - np.pi


def plan_route(
    occ_map: OccupancyMap,
    waypoints,
    clearance: float = 0.3,
    step: float = 0.4,
    wobble: float = 0.03,
    seed: int = 0,
    planner: RoutePlanner | None = None,
) -> np.ndarray:
    """Ground-truth map_from_base poses (N, 3) every `step` metres along the shortest route with
    `clearance` through `waypoints` (M, 2) in order; heading along the path plus wobble (radians).
    Pass a `planner` built for the same map and clearance to reuse its graph across routes."""
    planner = planner or RoutePlanner(occ_map, clearance)
    wps = [tuple(map(float, w[:2])) for w in waypoints]
    legs = [planner.leg(a, b) for a, b in zip(wps[:-1], wps[1:], strict=True)]
    polyline = np.vstack([legs[0]] + [leg[1:] for leg in legs[1:]]) if legs else np.array([wps[0], wps[0]])
    if len(polyline) < 2 or np.allclose(polyline, polyline[0]):
        return np.array([[wps[0][0], wps[0][1], 0.0]])
    xy, direction = resample(polyline, step)
    heading = smooth_headings(direction, wobble, np.random.default_rng(seed))
    return np.column_stack([xy, heading])
