"""Patch a site's occupancy map from new scans with known poses, inside the changed areas only.

The new scans are mapped on the old map's own grid (pipeline.mapping.occupancy, same cells, same
resolution). Where they disagree with the old map beyond a tolerance (`disagreement`: an obstacle seen
where the map has no wall within it, free space seen through a wall the scans do not see within it), or
observe a cell the map did not know, a cell of a changed area takes its new value; every other cell keeps
the old one. So a moved wall or a new cabinet enters the map, a wall's edge drawn a cell thicker or thinner
by another mapping does not, and nothing outside the areas that were re-captured can change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from pipeline.config import MappingConfig
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap


@dataclass(frozen=True)
class MapPatch:
    occ_map: OccupancyMap  # the patched map
    scans: int  # scans with ground truth used
    changed: np.ndarray  # (H, W) bool: cells whose value changed
    observed: np.ndarray  # (H, W) bool: cells of the changed areas the new scans observed


def scans_with_poses(runs: list[pa.Table], base_from_laser: tuple[float, float, float]):
    """(map_from_laser poses (N, 3), ranges (N, B), angle_min, angle_increment, range_max) of every scan with
    a ground-truth pose, or None when there is none."""
    from pipeline.runtime.sensor import laser_poses

    poses, ranges, laser = [], [], None
    for t in runs:
        gt = np.column_stack([t.column(c).to_numpy(zero_copy_only=False) for c in ("gt_x", "gt_y", "gt_theta")])
        gt = gt.astype(np.float64)
        keep = np.isfinite(gt).all(axis=1)
        if not keep.any():
            continue
        r = np.stack(t.column("ranges").to_pylist()).astype(np.float32)
        poses.append(gt[keep])
        ranges.append(r[keep])
        laser = (float(t.column("angle_min")[0].as_py()), float(t.column("angle_increment")[0].as_py()),
                 float(t.column("range_max")[0].as_py()))
    if not poses:
        return None
    return laser_poses(np.concatenate(poses), base_from_laser), np.concatenate(ranges), *laser


def disagreement(old: OccupancyMap, fresh: np.ndarray, observed: np.ndarray,
                 tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(new obstacles, walls gone), (H, W) bool: observed cells `fresh` calls occupied with no wall of `old`
    within `tolerance_m`, and walls of `old` that `fresh` observed free with no wall of its own within it."""
    from scipy.ndimage import distance_transform_edt

    seen_wall = observed & (fresh == OCCUPIED)
    seen_free = observed & (fresh == FREE)
    to_wall = distance_transform_edt(old.grid != OCCUPIED) * old.resolution
    to_seen_wall = distance_transform_edt(~seen_wall) * old.resolution
    new_obstacles = seen_wall & (old.grid != OCCUPIED) & (to_wall > tolerance_m + 1e-9)
    walls_gone = seen_free & (old.grid == OCCUPIED) & (to_seen_wall > tolerance_m + 1e-9)
    return new_obstacles, walls_gone


def fresh_map(old: OccupancyMap, runs: list[pa.Table], base_from_laser: tuple[float, float, float],
              cfg: MappingConfig, *, progress: bool = True) -> tuple[np.ndarray | None, int]:
    """(the runs' scans mapped on `old`'s grid (H, W), or None without scans with ground truth; scans used)."""
    from pipeline.mapping.occupancy import build_occupancy_map

    found = scans_with_poses(runs, base_from_laser)
    if found is None:
        return None, 0
    poses, ranges, angle_min, angle_increment, range_max = found
    # Scans in the grid's own frame (origin at 0, axes along the grid), so a rotated map origin works too.
    c, s = np.cos(-old.origin_yaw), np.sin(-old.origin_yaw)
    dx, dy = poses[:, 0] - old.origin_x, poses[:, 1] - old.origin_y
    local = np.column_stack([c * dx - s * dy, s * dx + c * dy, poses[:, 2] - old.origin_yaw])
    fresh = build_occupancy_map(local, ranges, angle_min, angle_increment, range_max,
                                cfg.model_copy(update={"resolution": old.resolution}),
                                frame=(0.0, 0.0, old.width, old.height), progress=progress)
    return fresh.grid, len(poses)


def patch_map(old: OccupancyMap, runs: list[pa.Table], base_from_laser: tuple[float, float, float],
              region: np.ndarray, cfg: MappingConfig, *, tolerance_m: float = 0.0,
              progress: bool = True) -> MapPatch:
    """`old` with the cells of `region` (H, W bool) where the runs' scans disagree with it (`disagreement`
    at `tolerance_m`; 0: every observed cell) or that it did not know replaced by their new value."""
    nothing = np.zeros(old.grid.shape, dtype=bool)
    if not region.any():
        return MapPatch(old, 0, nothing, nothing)
    fresh, scans = fresh_map(old, runs, base_from_laser, cfg, progress=progress)
    if fresh is None:
        return MapPatch(old, 0, nothing, nothing)
    observed = region & ((fresh == FREE) | (fresh == OCCUPIED))
    new_obstacles, walls_gone = disagreement(old, fresh, observed, tolerance_m)
    take = new_obstacles | walls_gone | (observed & (old.grid == UNKNOWN))
    grid = old.grid.copy()
    grid[take] = fresh[take]
    return MapPatch(OccupancyMap(grid=grid, resolution=old.resolution, origin_x=old.origin_x,
                                 origin_y=old.origin_y, origin_yaw=old.origin_yaw),
                    scans, grid != old.grid, observed)


def patch_figure(path, old: OccupancyMap, patch: MapPatch, region: np.ndarray) -> None:
    """PNG: the patched map in grey, the changed areas tinted blue, cells that became occupied red, freed green."""
    from PIL import Image

    grey = np.where(patch.occ_map.grid == OCCUPIED, 40, np.where(patch.occ_map.grid == FREE, 245, 170))
    rgb = np.repeat(grey[..., None], 3, axis=2).astype(np.float64)
    rgb[region] = 0.75 * rgb[region] + 0.25 * np.array([90, 140, 255])
    rgb[patch.changed & (patch.occ_map.grid == OCCUPIED)] = (220, 30, 30)
    rgb[patch.changed & (patch.occ_map.grid != OCCUPIED) & (old.grid == OCCUPIED)] = (30, 180, 60)
    img = Image.fromarray(np.flipud(rgb.astype(np.uint8)))  # row 0 is the lowest y: the image's bottom
    scale = max(1, int(np.ceil(600 / max(img.size))))
    img.resize((img.width * scale, img.height * scale), Image.NEAREST).save(path)
