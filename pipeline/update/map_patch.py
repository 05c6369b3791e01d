"""Patch a site's occupancy map from new scans with known poses, inside the changed areas only.

The new scans are mapped on the old map's own grid (pipeline.mapping.occupancy, same cells, same
resolution), each run on its own (`map_change`): a cell's new value is what most runs observing it say,
and a change counts only where most runs that looked there found it themselves, so a chair one run found
pushed aside or a person standing by the robot does not enter the map, while a moved wall or a new
cabinet does. Where they disagree with the old map beyond a tolerance (`disagreement`: an obstacle seen
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


def disagreement(old: OccupancyMap, fresh: np.ndarray, observed: np.ndarray, tolerance_m: float,
                 to_wall: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(new obstacles, walls gone), (H, W) bool: observed cells `fresh` calls occupied with no wall of `old`
    within `tolerance_m`, and walls of `old` that `fresh` observed free with no wall of its own within it.
    `to_wall`: `old`'s distance to its walls (m), when the caller compares several maps with it."""
    from scipy.ndimage import distance_transform_edt

    seen_wall = observed & (fresh == OCCUPIED)
    seen_free = observed & (fresh == FREE)
    if to_wall is None:
        to_wall = distance_transform_edt(old.grid != OCCUPIED) * old.resolution
    to_seen_wall = distance_transform_edt(~seen_wall) * old.resolution
    new_obstacles = seen_wall & (old.grid != OCCUPIED) & (to_wall > tolerance_m + 1e-9)
    walls_gone = seen_free & (old.grid == OCCUPIED) & (to_seen_wall > tolerance_m + 1e-9)
    return new_obstacles, walls_gone


@dataclass(frozen=True)
class MapChange:
    consensus: np.ndarray  # (H, W) grid values: per cell, the majority of the runs that observed it
    new_obstacles: np.ndarray  # (H, W) bool: persistent obstacles the old map lacks
    walls_gone: np.ndarray  # (H, W) bool: walls of the old map persistently seen free
    scans: int  # scans with ground truth used
    runs: int  # runs with ground truth used


def map_change(old: OccupancyMap, runs: list[pa.Table], base_from_laser: tuple[float, float, float],
               cfg: MappingConfig, tolerance_m: float, *, progress: bool = True) -> MapChange | None:
    """Where the runs' scans find the building changed against `old` (None without scans with ground truth).

    Each run is mapped alone on `old`'s grid. `consensus` holds, per cell, the value most runs that observed
    it give it (UNKNOWN where none did or they split evenly). A change is `disagreement` of the consensus
    with `old`, kept only in regions (the cells any run found changed, grouped when closer than
    `tolerance_m` and a cell) that more than half of the runs observing their cells found changed
    themselves: a chair one run found pushed aside is seen where it stood by the other runs (they observe
    its faces, not its inside), and a person standing by one run is not there for the next; a moved wall
    is seen by every run passing it. One run is its own majority: what it saw is taken as it is.
    """
    from scipy.ndimage import binary_dilation, distance_transform_edt, label

    from pipeline.mapping.occupancy import build_occupancy_map
    from pipeline.progress import progress_bar

    mapped = [f for f in (scans_with_poses([t], base_from_laser) for t in runs) if f is not None]
    if not mapped:
        return None
    # Scans in the grid's own frame (origin at 0, axes along the grid), so a rotated map origin works too.
    c, s = np.cos(-old.origin_yaw), np.sin(-old.origin_yaw)
    on_grid = cfg.model_copy(update={"resolution": old.resolution})
    seen = np.zeros(old.grid.shape, dtype=np.int32)
    occupied = np.zeros(old.grid.shape, dtype=np.int32)
    per_run = []  # (observed cells packed into bits, flat indices of the cells the run alone finds changed)
    to_wall = distance_transform_edt(old.grid != OCCUPIED) * old.resolution  # the same for every run
    scans = 0
    for poses, ranges, angle_min, angle_increment, range_max in progress_bar(
            mapped, desc="map the new runs", unit="run", enabled=progress and len(mapped) > 1):
        dx, dy = poses[:, 0] - old.origin_x, poses[:, 1] - old.origin_y
        local = np.column_stack([c * dx - s * dy, s * dx + c * dy, poses[:, 2] - old.origin_yaw])
        grid = build_occupancy_map(local, ranges, angle_min, angle_increment, range_max, on_grid,
                                   frame=(0.0, 0.0, old.width, old.height),
                                   progress=progress and len(mapped) == 1).grid
        observed = (grid == FREE) | (grid == OCCUPIED)
        seen += observed
        occupied += grid == OCCUPIED
        new, gone = disagreement(old, grid, observed, tolerance_m, to_wall)
        per_run.append((np.packbits(observed, axis=None), np.flatnonzero(new | gone)))
        scans += len(poses)
    consensus = np.full(old.grid.shape, UNKNOWN, dtype=old.grid.dtype)
    consensus[2 * occupied > seen] = OCCUPIED
    consensus[(seen > 0) & (2 * occupied < seen)] = FREE
    new_obstacles, walls_gone = disagreement(old, consensus, consensus != UNKNOWN, tolerance_m, to_wall)

    # Regions: the cells some run found changed, grouped when closer than the tolerance and a cell. A run
    # looked at a region when it observed one of those cells (a pushed chair's faces, where it stood).
    changed_somewhere = np.zeros(old.grid.size, dtype=bool)
    for _, flat in per_run:
        changed_somewhere[flat] = True
    grow = int(np.ceil(tolerance_m / old.resolution)) + 1
    regions, n = label(binary_dilation(changed_somewhere.reshape(old.grid.shape), iterations=grow),
                       structure=np.ones((3, 3)))
    label_of_cell = regions.ravel()  # every cell of a grown region, for the consensus's changes
    regions = np.where(changed_somewhere, label_of_cell, 0)
    found = np.zeros(n + 1, dtype=np.int64)  # runs that found the region changed
    looked = np.zeros(n + 1, dtype=np.int64)  # runs that observed some of its cells
    for packed, flat in per_run:
        observed = np.unpackbits(packed, count=old.grid.size).astype(bool)
        looked[np.unique(regions[observed])] += 1
        found[np.unique(regions[flat])] += 1
    persistent = 2 * found > looked
    persistent[0] = False
    keep = persistent[label_of_cell].reshape(old.grid.shape)
    return MapChange(consensus, new_obstacles & keep, walls_gone & keep, scans, len(mapped))


def patch_map(old: OccupancyMap, runs: list[pa.Table], base_from_laser: tuple[float, float, float],
              region: np.ndarray, cfg: MappingConfig, *, tolerance_m: float = 0.0,
              progress: bool = True) -> MapPatch:
    """`old` with the cells of `region` (H, W bool) where the runs find the building changed (`map_change`
    at `tolerance_m`; 0: every observed cell that differs) or that it did not know replaced by the runs'
    consensus."""
    nothing = np.zeros(old.grid.shape, dtype=bool)
    if not region.any():
        return MapPatch(old, 0, nothing, nothing)
    change = map_change(old, runs, base_from_laser, cfg, tolerance_m, progress=progress)
    if change is None:
        return MapPatch(old, 0, nothing, nothing)
    observed = region & (change.consensus != UNKNOWN)
    take = region & (change.new_obstacles | change.walls_gone | (observed & (old.grid == UNKNOWN)))
    grid = old.grid.copy()
    grid[take] = change.consensus[take]
    return MapPatch(OccupancyMap(grid=grid, resolution=old.resolution, origin_x=old.origin_x,
                                 origin_y=old.origin_y, origin_yaw=old.origin_yaw),
                    change.scans, grid != old.grid, observed)


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
