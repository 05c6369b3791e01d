"""Occupancy mapping with known poses, checked against geometry: an analytic room and single beams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.config import MappingConfig
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from pipeline.mapping.occupancy import MAX_MAP_CELLS, MapTooLargeError, build_occupancy_map, endpoint_occupied_share
from pipeline.mapping.preview import write_preview
from tests.fixtures.carmen_logs import ROOM, room_poses, room_ranges

RANGE_MAX = 40.0
INC = math.pi / 180


def _room(n_scans: int = 40, n_beams: int = 181, **cfg) -> tuple[OccupancyMap, np.ndarray, np.ndarray]:
    poses = room_poses(n_scans)
    ranges = room_ranges(poses, -math.pi / 2 + INC * np.arange(n_beams)).astype(np.float32)
    occ = build_occupancy_map(poses, ranges, -math.pi / 2, INC, RANGE_MAX, MappingConfig(**cfg), progress=False)
    return occ, poses, ranges


def _cell_centres(occ: OccupancyMap) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.indices(occ.grid.shape)
    return occ.cell_to_world(rows, cols)


def test_room_map_has_walls_on_the_rectangle_and_free_space_inside():
    occ, poses, ranges = _room(resolution=0.05, margin_m=0.5)
    x0, y0, x1, y1 = ROOM
    # The grid spans the walls plus the margin, snapped to whole cells (endpoints may round a hair outside).
    assert x0 - 0.55 - 1e-9 <= occ.origin_x <= x0 - 0.5 and y0 - 0.55 - 1e-9 <= occ.origin_y <= y0 - 0.5
    assert occ.width * 0.05 >= x1 + 0.5 and occ.height * 0.05 >= y1 + 0.5
    cx, cy = _cell_centres(occ)
    # Distance of each cell centre to the nearest wall line (inside) or to the rectangle (outside).
    inside = (cx > x0) & (cx < x1) & (cy > y0) & (cy < y1)
    to_wall = np.minimum.reduce([np.abs(cx - x0), np.abs(cx - x1), np.abs(cy - y0), np.abs(cy - y1)])
    wall = inside & (to_wall < 0.05) | ~inside & (
        np.maximum(np.maximum(x0 - cx, cx - x1), np.maximum(y0 - cy, cy - y1)) < 0.05
    )
    interior = inside & (to_wall > 0.15)
    outside = ~inside & ~wall
    # Occupied cells are only at the walls; nothing beyond them was observed.
    assert occ.occupied[~wall].sum() == 0
    assert (occ.grid[outside] == UNKNOWN).all()
    # The interior (over 3 cells from a wall) is free, up to a few cells too rarely seen to reach free_thresh.
    assert (occ.grid[interior] == FREE).mean() > 0.99
    assert not occ.occupied[interior].any()
    # Each wall is traced along its whole length. The wall lines lie on cell borders, so the endpoints
    # (rounded a hair to either side) occupy one of the two cells beside the line: accept either.
    along = np.linspace(0.3, 3.7, 60)
    for px, py, normal in [
        (x0 + 1.5 * along, np.full(60, y0), (0, 1)),
        (x0 + 1.5 * along, np.full(60, y1), (0, 1)),
        (np.full(60, x0), y0 + along, (1, 0)),
        (np.full(60, x1), y0 + along, (1, 0)),
    ]:
        e = 0.01 * np.array(normal)
        on_wall = (occ.value_at(px + e[0], py + e[1]) == OCCUPIED) | (occ.value_at(px - e[0], py - e[1]) == OCCUPIED)
        assert on_wall.mean() > 0.97
    share0 = endpoint_occupied_share(occ, poses, ranges, -math.pi / 2, INC, RANGE_MAX, 0)
    share1 = endpoint_occupied_share(occ, poses, ranges, -math.pi / 2, INC, RANGE_MAX, 1)
    # Exact-cell share is below 1 only because beams grazing a wall clear some of its cells (measured
    # 0.93 at 0.05 m, 0.99 at 0.1 m); one cell of tolerance finds every endpoint on the wall.
    assert share0 > 0.9 and share1 == pytest.approx(1.0)


def test_single_beam_traverses_exactly_the_cells_before_its_endpoint():
    """A beam along +x from the middle of a cell: the 20 cells it crosses are free, the 21st occupied."""
    cfg = MappingConfig(resolution=0.1, margin_m=0.0, log_odds_miss=2.0)  # one miss is enough for "free"
    poses = np.array([[0.05, 0.05, 0.0]])
    ranges = np.array([[2.02, RANGE_MAX]], dtype=np.float32)  # the second beam (at +90 deg) has no return
    occ = build_occupancy_map(poses, ranges, 0.0, math.pi / 2, RANGE_MAX, cfg, progress=False)
    row, col = occ.world_to_cell(np.array([0.05]), np.array([0.05]))
    line = occ.grid[row[0]]
    assert (line[col[0] : col[0] + 20] == FREE).all()
    assert line[col[0] + 20] == OCCUPIED
    # Nothing else was observed: in particular the no-return beam cleared nothing.
    assert (occ.grid != UNKNOWN).sum() == 21


def test_diagonal_beam_cells_lie_on_the_segment():
    cfg = MappingConfig(resolution=0.05, margin_m=0.2, log_odds_miss=2.0)
    poses = np.array([[0.013, 0.021, 0.0]])
    angle = 0.61
    occ = build_occupancy_map(poses, np.array([[3.0]], np.float32), angle, 0.0, RANGE_MAX, cfg, progress=False)
    rows, cols = np.nonzero(occ.grid == FREE)
    # Reference: cells a very finely sampled segment passes through (strictly before the endpoint).
    d = np.linspace(0, 3.0, 300_001)[:-1]
    ref_r, ref_c = occ.world_to_cell(0.013 + d * math.cos(angle), 0.021 + d * math.sin(angle))
    ref = set(zip(ref_r.tolist(), ref_c.tolist(), strict=True))
    end = occ.world_to_cell(0.013 + 3 * math.cos(angle), 0.021 + 3 * math.sin(angle))
    free = set(zip(rows.tolist(), cols.tolist(), strict=True))
    assert free <= ref  # never a cell off the beam
    assert len(free) >= 0.9 * (len(ref) - 1)  # at most corner-grazing cells are skipped at resolution/2 steps
    assert occ.grid[end[0], end[1]] == OCCUPIED


def test_hit_beats_miss_within_a_scan_and_clamp_is_applied_per_scan():
    """Two beams of one scan: one ends in a cell another passes through; the cell counts as hit only."""
    cfg = MappingConfig(resolution=0.1, margin_m=0.0)
    poses = np.array([[0.05, 0.05, 0.0]])
    ranges = np.array([[1.0, 3.0]], dtype=np.float32)  # both along +x (increment 0)
    occ = build_occupancy_map(poses, ranges, 0.0, 0.0, RANGE_MAX, cfg, progress=False)
    assert occ.value_at(1.05, 0.05) == OCCUPIED  # one hit (L = 0.85 -> p = 0.70), the miss was dropped
    # Many identical scans: log-odds saturate at the clamp, so chunking cannot change the result.
    many_poses, many_ranges = np.repeat(poses, 50, axis=0), np.repeat(ranges, 50, axis=0)
    maps = [
        build_occupancy_map(
            many_poses,
            many_ranges,
            0.0,
            0.0,
            RANGE_MAX,
            cfg.model_copy(update={"chunk_scans": k}),
            progress=False,
        ).grid
        for k in (1, 7, 64)
    ]
    assert all((m == maps[0]).all() for m in maps)


def test_room_map_does_not_depend_on_chunk_size():
    a, _, _ = _room(n_scans=30, chunk_scans=1, resolution=0.1)
    b, _, _ = _room(n_scans=30, chunk_scans=64, resolution=0.1)
    np.testing.assert_array_equal(a.grid, b.grid)


def test_a_given_frame_maps_on_that_grid_and_ignores_beams_that_leave_it():
    occ, poses, ranges = _room(n_scans=20, resolution=0.1)
    frame = (occ.origin_x, occ.origin_y, occ.width, occ.height)
    same = build_occupancy_map(poses, ranges, -math.pi / 2, INC, RANGE_MAX, MappingConfig(resolution=0.1),
                               frame=frame, progress=False)
    np.testing.assert_array_equal(same.grid, occ.grid)
    # The left half of that grid: cells there see only the beams that stay in it, so no wall of the right half
    # is folded onto its border, and what it holds agrees with the full map wherever it observed anything.
    half = build_occupancy_map(poses, ranges, -math.pi / 2, INC, RANGE_MAX, MappingConfig(resolution=0.1),
                               frame=(occ.origin_x, occ.origin_y, occ.width // 2, occ.height), progress=False)
    assert half.grid.shape == (occ.height, occ.width // 2)
    seen = half.grid != UNKNOWN
    border = half.grid[:, -1] == OCCUPIED
    assert seen.any() and (occ.grid[:, occ.width // 2 - 1][border] == OCCUPIED).all()
    assert np.mean(half.grid[seen] == occ.grid[:, : occ.width // 2][seen]) > 0.97


def test_endpoint_share_tolerance_and_outside():
    grid = np.zeros((10, 10), dtype=np.int8)
    grid[5, 5] = OCCUPIED
    occ = OccupancyMap(grid=grid, resolution=0.1)
    # Endpoints: on the occupied cell (0.55, 0.55), its neighbour, two cells away, outside the map.
    targets = [(0.55, 0.55), (0.65, 0.55), (0.75, 0.55), (5.0, 0.0)]
    poses = np.array([[0.0, 0.0, math.atan2(y, x)] for x, y in targets])  # one scan per target, one beam at 0
    ranges = np.array([[math.hypot(x, y)] for x, y in targets])
    share = [endpoint_occupied_share(occ, poses, ranges, 0.0, 0.0, RANGE_MAX, k) for k in (0, 1, 2)]
    assert share == [pytest.approx(0.25), pytest.approx(0.5), pytest.approx(0.75)]
    assert math.isnan(endpoint_occupied_share(occ, poses, np.full((4, 1), RANGE_MAX), 0.0, 0.0, RANGE_MAX))


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError):
        build_occupancy_map(np.zeros((3, 3)), np.zeros((2, 5)), 0.0, 0.1, RANGE_MAX, progress=False)


def test_non_finite_poses_are_rejected():
    poses = np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    with pytest.raises(ValueError, match="row 1"):
        build_occupancy_map(poses, np.ones((2, 3)), 0.0, 0.1, RANGE_MAX, progress=False)


@pytest.mark.parametrize("far", [1e7, 1e300, 1.7e308])
def test_a_far_pose_is_refused_before_the_grid_is_allocated(far):
    """One pose at x = 1e7 asked for a 60 GiB grid (MemoryError); now a MapTooLargeError, before allocating."""
    poses = np.array([[0.0, 0.0, 0.0], [far, 0.0, 0.0], [-far, 1.0, 0.0]][: 2 if far < 1e300 else 3])
    ranges = np.ones((len(poses), 3))
    with pytest.raises(MapTooLargeError) as info:
        build_occupancy_map(poses, ranges, 0.0, 0.1, RANGE_MAX, MappingConfig(resolution=0.05), progress=False)
    assert f"{MAX_MAP_CELLS:,} cells allowed" in str(info.value) and "at 0.05 m" in str(info.value)
    # A given frame (map patching) is checked the same way.
    with pytest.raises(MapTooLargeError):
        build_occupancy_map(poses[:1], ranges[:1], 0.0, 0.1, RANGE_MAX, MappingConfig(resolution=0.05),
                            frame=(0.0, 0.0, 100_000, 100_000), progress=False)


def test_preview_is_a_png_and_deterministic(tmp_path):
    occ, poses, _ = _room(n_scans=10, resolution=0.1)
    a = write_preview(tmp_path / "a.png", occ, poses, "room: test")
    b = write_preview(tmp_path / "b.png", occ, poses, "room: test")
    data = a.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data == b.read_bytes()
    assert not list(tmp_path.glob("*.tmp-write"))
