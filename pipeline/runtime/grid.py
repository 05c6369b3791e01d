"""The laser map as the filter sees it: occupied / free cells, the distance field, free-space sampling.

Built once from an `OccupancyMap` (map_server semantics, row 0 = lowest y). The distance field holds,
for every cell, the distance from its centre to the nearest occupied cell's centre (scipy's exact
Euclidean transform), capped at `max_distance`: the likelihood field model looks endpoints up in it,
so an endpoint's distance is that of its cell (quantised to the resolution, as in nav2).
The grid is padded by one cell on every side whose distance is `max_distance`, so clipping an index
into the padded grid sends every off-map endpoint to a "nothing near" cell without a branch.
Unknown cells count as not free (no particle is born there) and not occupied (no beam ends there).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap


@dataclass(frozen=True)
class LaserMap:
    occupied: np.ndarray  # (H, W) bool
    free: np.ndarray  # (H, W) bool
    resolution: float
    origin_x: float
    origin_y: float
    max_distance: float
    distance_padded: np.ndarray  # (H + 2, W + 2) float32, m, capped at max_distance
    free_cells: np.ndarray  # (K,) int64 flat indices of free cells (unpadded grid)
    source: OccupancyMap  # the map it was built from: its frame arithmetic (world_to_cell, value_at) is reused

    @classmethod
    def from_occupancy(cls, occ_map: OccupancyMap, max_distance: float = 2.0) -> LaserMap:
        if occ_map.origin_yaw:
            raise ValueError("maps with a rotated origin are not supported by the filter; re-save with yaw 0")
        occupied = np.asarray(occ_map.grid) >= OCCUPIED * 0.65  # occupied_thresh on scale maps, 100 on trinary
        free = np.asarray(occ_map.grid) == 0
        if not occupied.any():
            raise ValueError("the map has no occupied cell: nothing for a laser to see")
        if not free.any():
            raise ValueError("the map has no free cell: nowhere for the robot to be")
        dist = distance_transform_edt(~occupied).astype(np.float32) * np.float32(occ_map.resolution)
        np.minimum(dist, np.float32(max_distance), out=dist)
        padded = np.pad(dist, 1, constant_values=np.float32(max_distance))
        return cls(occupied, free, float(occ_map.resolution), float(occ_map.origin_x), float(occ_map.origin_y),
                   float(max_distance), padded, np.flatnonzero(free), occ_map)

    @property
    def height(self) -> int:
        return int(self.occupied.shape[0])

    @property
    def width(self) -> int:
        return int(self.occupied.shape[1])

    @property
    def free_area_m2(self) -> float:
        return float(len(self.free_cells) * self.resolution**2)

    def fingerprint(self) -> str:
        """sha256 of the grid and its frame: what caches derived from the map are keyed by."""
        h = hashlib.sha256()
        h.update(np.packbits(self.occupied).tobytes())
        h.update(np.packbits(self.free).tobytes())
        h.update(np.array([self.resolution, self.origin_x, self.origin_y], dtype=np.float64).tobytes())
        return h.hexdigest()

    def cells(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of map-frame points, possibly outside the grid."""
        return self.source.world_to_cell(x, y)

    def cell_of(self, x: float, y: float) -> tuple[int, int] | None:
        """(row, col) of one map-frame point, or None off the grid (or not finite); as `cells` rounds it."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return None
        col = math.floor((x - self.origin_x) / self.resolution)
        row = math.floor((y - self.origin_y) / self.resolution)
        return (row, col) if 0 <= row < self.height and 0 <= col < self.width else None

    def known(self, x: float, y: float) -> bool:
        """Whether one map-frame point lies on the grid in a cell the map knows (free, occupied or between):
        nowhere else can a robot be, so a belief elsewhere is wrong (`AdaptiveMCL` never tracks there)."""
        cell = self.cell_of(x, y)
        return cell is not None and bool(self.source.grid[cell] >= 0)

    def is_free(self, x, y) -> np.ndarray:
        return self.source.value_at(x, y) == FREE

    def distance_at(self, x, y) -> np.ndarray:
        """Distance field at map-frame points (max_distance off the map)."""
        row, col = self.cells(x, y)
        row = np.clip(row + 1, 0, self.height + 1)
        col = np.clip(col + 1, 0, self.width + 1)
        return self.distance_padded[row, col]

    def sample_free(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) poses uniform over the free space (uniform within a cell) with uniform headings."""
        return self._poses_in(self.free_cells[rng.integers(0, len(self.free_cells), size=n)], rng)

    def _poses_in(self, cells: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One pose per flat cell index: uniform within the cell, uniform heading."""
        row, col = np.divmod(cells, self.width)
        u = rng.random((3, len(cells)))
        x = self.origin_x + (col + u[0]) * self.resolution
        y = self.origin_y + (row + u[1]) * self.resolution
        return np.column_stack([x, y, (u[2] * 2.0 - 1.0) * np.pi])

    def sample_regions(self, cell_region: np.ndarray, weights: np.ndarray, n: int,
                       rng: np.random.Generator) -> np.ndarray:
        """(n, 3) poses over labelled parts of the free space: `cell_region` (K,) gives each free cell's
        region (-1: none), `weights` (R,) each region's share of the particles; uniform within a region
        (and within a cell), uniform headings. Regions without a free cell get no particle."""
        cell_region = np.asarray(cell_region, dtype=np.int64)
        if cell_region.shape != self.free_cells.shape:
            raise ValueError(f"cell_region has {cell_region.shape} entries, the map {len(self.free_cells)} free cells")
        w = np.asarray(weights, dtype=np.float64).copy()
        sizes = np.bincount(cell_region[cell_region >= 0], minlength=len(w))[: len(w)]
        w[sizes == 0] = 0.0
        if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError("no region with free cells has a positive weight")
        counts = rng.multinomial(n, w / w.sum())
        order = np.argsort(cell_region, kind="stable")
        starts = np.searchsorted(cell_region[order], np.arange(len(w)))
        picks = [order[starts[r] + rng.integers(0, sizes[r], size=c)] for r, c in enumerate(counts) if c]
        return self._poses_in(self.free_cells[np.concatenate(picks)], rng)

    def sample_around(self, centres: np.ndarray, weights: np.ndarray, n: int, std_xy: float, std_theta: float,
                      rng: np.random.Generator, tries: int = 8) -> np.ndarray:
        """(n, 3) poses drawn around weighted centre poses (Gaussian), redrawn until they lie in free space.

        Centres are picked in proportion to `weights`; `std_theta` is one spread or one per centre. A draw
        that stays outside free space after `tries` redraws keeps its centre's position (a candidate itself
        may sit in a cell the map calls unknown).
        """
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(weights, dtype=np.float64)
        w = w / w.sum()
        which = rng.choice(len(centres), size=n, p=w)
        std_theta = np.asarray(std_theta, dtype=np.float64)
        return self.jitter(centres[which], std_xy, std_theta if std_theta.ndim == 0 else std_theta[which], rng, tries)

    def jitter(self, base: np.ndarray, std_xy: float, std_theta: float, rng: np.random.Generator,
               tries: int = 8) -> np.ndarray:
        """One Gaussian draw around each pose of `base` (N, 3), redrawn until it lies in free space (after
        `tries` redraws it keeps the pose's position); `std_theta` one spread or (N,); headings wrapped to
        [-pi, pi)."""
        base = np.asarray(base, dtype=np.float64).reshape(-1, 3)
        out = base.copy()
        std = np.empty((len(base), 3))
        std[:, :2], std[:, 2] = std_xy, std_theta
        todo = np.arange(len(base))
        for _ in range(tries):
            noise = rng.standard_normal((len(todo), 3)) * std[todo]
            out[todo] = base[todo] + noise
            todo = todo[~self.is_free(out[todo, 0], out[todo, 1])]
            if len(todo) == 0:
                break
        out[todo, :2] = base[todo, :2]
        out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return out
