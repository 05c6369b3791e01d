"""The new runs' map is their majority: what every run sees changes the map, what one run saw does not."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline.config import MappingConfig
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from pipeline.sitegen.laser import LaserScanner
from pipeline.update.map_patch import disagreement, map_change, patch_map

RES = 0.05


def _room() -> OccupancyMap:
    """An 8 x 6 m room, walls 0.2 m thick, free inside, with a cabinet (1 x 0.5 m) and a chair in the map."""
    grid = np.full((int(6.4 / RES), int(8.4 / RES)), FREE, dtype=np.int8)
    grid[:4], grid[-4:], grid[:, :4], grid[:, -4:] = OCCUPIED, OCCUPIED, OCCUPIED, OCCUPIED
    occ = OccupancyMap(grid=grid, resolution=RES, origin_x=-0.2, origin_y=-0.2)
    _box(occ, 6.0, 5.0, 1.0, 0.5, OCCUPIED)
    _box(occ, 2.0, 4.5, 0.6, 0.6, OCCUPIED)
    return occ


def _box(occ: OccupancyMap, x: float, y: float, w: float, h: float, value: int) -> np.ndarray:
    """Set the cells of an axis-aligned box centred at (x, y) to `value`, in place; returns its mask."""
    r0, c0 = occ.world_to_cell(np.array([x - w / 2]), np.array([y - h / 2]))
    r1, c1 = occ.world_to_cell(np.array([x + w / 2]), np.array([y + h / 2]))
    mask = np.zeros(occ.grid.shape, dtype=bool)
    mask[int(r0[0]):int(r1[0]) + 1, int(c0[0]):int(c1[0]) + 1] = True
    occ.grid[mask] = value
    return mask


def _run(world: OccupancyMap, seed: int) -> pa.Table:
    """A lap around the room's middle, 80 scans of 361 beams over 360 degrees, at ground-truth poses."""
    t = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    poses = np.column_stack([4.0 + 2.2 * np.cos(t), 3.0 + 1.4 * np.sin(t), t + np.pi / 2])
    scanner = LaserScanner(world, beams=361, fov_deg=359.0, range_max=12.0, noise_sigma=0.005, dropout=0.0,
                           seed=seed)
    ranges = scanner.cast_many(poses)
    n = len(poses)
    return pa.table({"gt_x": poses[:, 0], "gt_y": poses[:, 1], "gt_theta": poses[:, 2],
                     "ranges": pa.array(list(ranges), pa.list_(pa.float32())),
                     "angle_min": [scanner.angle_min] * n, "angle_increment": [scanner.angle_increment] * n,
                     "range_max": [scanner.range_max] * n})


def _changed_building(transient: bool) -> tuple[OccupancyMap, dict]:
    """The room as the runs find it: the cabinet gone, a new one in (2, 1.5); with `transient`, the chair
    pushed from (2, 4.5) to (4.5, 4.5), as one run may find it."""
    old = _room()
    world = OccupancyMap(grid=old.grid.copy(), resolution=RES, origin_x=old.origin_x, origin_y=old.origin_y)
    masks = {"gone": _box(world, 6.0, 5.0, 1.0, 0.5, FREE), "new": _box(world, 2.0, 1.5, 1.0, 0.5, OCCUPIED)}
    if transient:
        masks["chair_was"] = _box(world, 2.0, 4.5, 0.6, 0.6, FREE)
        masks["chair"] = _box(world, 4.5, 4.5, 0.6, 0.6, OCCUPIED)
    return world, masks


def _near(mask: np.ndarray, cells: int = 2) -> np.ndarray:
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=cells)


def test_a_change_every_run_sees_enters_the_map_and_one_run_s_pushed_chair_does_not():
    old = _room()
    with_chair, masks = _changed_building(transient=True)
    without, _ = _changed_building(transient=False)
    runs = [_run(with_chair, 0), _run(without, 1), _run(without, 2)]
    change = map_change(old, runs, (0.0, 0.0, 0.0), MappingConfig(), 0.1, progress=False)
    assert change.scans == 240 and change.runs == 3
    new, gone = change.new_obstacles, change.walls_gone
    assert new.sum() > 20 and gone.sum() > 20
    assert np.all(_near(masks["new"])[new]), "a new obstacle away from the new cabinet"
    assert np.all(_near(masks["gone"])[gone]), "a wall gone away from the old cabinet"
    # Only the first run saw the chair's place empty (the others see its faces, never its inside) and
    # the chair at its new place: neither is a change of the building.
    assert not (new & _near(masks["chair"])).any() and not (gone & _near(masks["chair_was"])).any()
    # Without the vote, the consensus alone calls the chair's inside gone: the first run is its only witness.
    _, gone_by_consensus = disagreement(old, change.consensus, change.consensus != UNKNOWN, 0.1)
    assert (gone_by_consensus & masks["chair_was"]).sum() > 10

    # The chair's run alone is its own majority: it cannot tell a pushed chair from a moved cabinet.
    alone = map_change(old, runs[:1], (0.0, 0.0, 0.0), MappingConfig(), 0.1, progress=False)
    assert (alone.new_obstacles & masks["chair"]).sum() > 10 and (alone.walls_gone & masks["chair_was"]).sum() > 10


def test_the_consensus_is_each_cell_s_majority_of_the_runs_maps_and_a_tie_is_unknown():
    from pipeline.mapping.occupancy import build_occupancy_map
    from pipeline.update.map_patch import scans_with_poses

    old = _room()
    with_chair, _ = _changed_building(transient=True)
    without, _ = _changed_building(transient=False)
    runs = [_run(with_chair, 0), _run(without, 1)]
    fresh = map_change(old, runs, (0.0, 0.0, 0.0), MappingConfig(), 0.1, progress=False).consensus
    # Brute force: each run mapped on its own, cell by cell the vote.
    grids = []
    for t in runs:
        poses, ranges, a0, da, rmax = scans_with_poses([t], (0.0, 0.0, 0.0))
        poses = poses - np.array([old.origin_x, old.origin_y, 0.0])
        grids.append(build_occupancy_map(poses, ranges, a0, da, rmax, MappingConfig(resolution=RES),
                                         frame=(0.0, 0.0, old.width, old.height), progress=False).grid)
    a, b = grids
    expect = np.where(a == b, a, UNKNOWN)  # two runs: agreement, or a tie (one unknown: the other's value)
    expect = np.where((a == UNKNOWN) & (b != UNKNOWN), b, expect)
    expect = np.where((b == UNKNOWN) & (a != UNKNOWN), a, expect)
    assert np.array_equal(fresh, expect)
    assert (a != b).any() and (fresh == UNKNOWN).sum() > (old.grid == UNKNOWN).sum()


def test_patch_takes_the_persistent_change_inside_the_region_only():
    old = _room()
    with_chair, masks = _changed_building(transient=True)
    without, _ = _changed_building(transient=False)
    runs = [_run(with_chair, 0), _run(without, 1), _run(without, 2)]
    left = np.zeros(old.grid.shape, dtype=bool)
    left[:, : old.grid.shape[1] // 2] = True  # the new cabinet's and the chair's half, not the old cabinet's
    p = patch_map(old, runs, (0.0, 0.0, 0.0), left, MappingConfig(), tolerance_m=0.1, progress=False)
    assert p.changed.any() and not (p.changed & ~left).any()
    assert np.all(p.occ_map.grid[p.changed] == OCCUPIED)
    assert np.all(_near(masks["new"])[p.changed]) and (p.changed & masks["new"]).sum() > 20
    assert np.all(p.occ_map.grid[masks["gone"]] == OCCUPIED), "the old cabinet is outside the region"
