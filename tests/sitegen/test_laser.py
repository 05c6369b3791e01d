"""The site's map rasterisation and simulated laser, checked against geometry written out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN
from pipeline.io.site import Laser
from pipeline.mapping.occupancy import endpoint_occupied_share
from pipeline.sitegen.laser import (
    LaserScanner,
    displace_furniture,
    laser_poses,
    laser_world_grid,
    rasterise_map,
    walking_people,
)
from pipeline.sitegen.scene import Rect, Room, Scene, SceneObject, Wall
from tests.sitegen.small_floor import CHAIR, CORE_CABINET, DESK, box_room, small_floor


def _box_distances(pose, angles, x0=0.1, y0=0.1, x1=5.9, y1=3.9) -> np.ndarray:
    """Closed form: distance from inside a rectangle to its boundary along each beam."""
    a = pose[2] + angles
    dx, dy = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(dx > 0, (x1 - pose[0]) / dx, np.where(dx < 0, (x0 - pose[0]) / dx, np.inf))
        ty = np.where(dy > 0, (y1 - pose[1]) / dy, np.where(dy < 0, (y0 - pose[1]) / dy, np.inf))
    return np.minimum(tx, ty)


def _exact(world, **kw) -> LaserScanner:
    return LaserScanner(world, noise_sigma=0.0, dropout=0.0, **kw)


def test_map_frame_and_what_is_occupied_free_and_unknown():
    occ = rasterise_map(small_floor(), 0.05)
    assert (occ.origin_x, occ.origin_y, occ.resolution) == (-1.0, -1.0, 0.05)
    assert occ.grid.shape == (200, 280) and occ.grid.dtype == np.int8

    def at(x, y):
        return int(occ.value_at(x, y))

    assert at(1.0, 3.0) == OCCUPIED and at(1.0, 3.09) == OCCUPIED and at(1.0, 3.11) == FREE  # wall and its face
    assert at(2.5, 3.0) == FREE and at(7.5, 3.0) == FREE  # doorways
    assert at(10.5, 3.0) == OCCUPIED  # closed door
    assert at(4.6, 0.0) == OCCUPIED and at(9.8, 0.0) == OCCUPIED  # window, closed exterior door
    assert at(4.0, 1.5) == FREE and at(3.0, 4.5) == FREE and at(9.0, 5.0) == FREE
    assert at(-0.5, 4.0) == UNKNOWN and at(12.5, 4.0) == UNKNOWN and at(6.0, -0.5) == UNKNOWN  # outside
    assert at(11.0, 7.5) == UNKNOWN and at(11.0, 7.0) == UNKNOWN  # closed core: its cabinet is not mapped either
    assert at(10.0, 7.0) == OCCUPIED  # the core's own walls are
    assert at(11.0, 1.5) == OCCUPIED and at(8.0, 7.5) == OCCUPIED  # plant, cabinet
    assert at(5.0, 0.13) == FREE  # the poster does not block the laser
    # The desk faces yaw = 0.3 rad, so its 1.4 m width runs along yaw + pi/2 and its 0.7 m depth along yaw:
    # points of its footprint are occupied, points just beyond its rotated edges are free.
    wx, wy = -math.sin(DESK.yaw), math.cos(DESK.yaw)  # width axis
    dx, dy = math.cos(DESK.yaw), math.sin(DESK.yaw)  # depth axis (towards its front)
    for u, v in ((0.0, 0.0), (0.6, 0.3), (-0.6, -0.3), (0.6, -0.3), (-0.6, 0.3)):
        assert at(DESK.x + u * wx + v * dx, DESK.y + u * wy + v * dy) == OCCUPIED
    for u, v in ((0.0, 0.5), (0.0, -0.5), (0.85, 0.0), (-0.85, 0.0)):
        assert at(DESK.x + u * wx + v * dx, DESK.y + u * wy + v * dy) == FREE
    assert at(CHAIR.x + 0.2, CHAIR.y + 0.2) == OCCUPIED and at(CHAIR.x + 0.3, CHAIR.y) == FREE


def test_thin_diagonal_wall_still_stops_every_beam():
    """A 1 cm wall at 32 degrees is thinner than a cell: it must still rasterise to an unbroken barrier."""
    wall = Wall(1.0, 1.0, 5.0, 3.5, thickness=0.01, height=2.5, material=0)
    scene = Scene("thin", 0, Rect(0, 0, 6, 4.5), [wall], [], [], [], 2.5, ())
    scanner = _exact(rasterise_map(scene, 0.05), beams=2001, fov_deg=90.0)
    theta = math.atan2(2.5, 4.0)
    normal = np.array([math.sin(theta), -math.cos(theta)])  # from above the wall towards it
    pose = np.array([*(np.array([3.0, 2.25]) - 0.8 * normal), math.atan2(normal[1], normal[0])])
    ranges = scanner.cast(pose, noisy=False)
    expected = 0.8 / np.cos(scanner.angles)  # distance to the wall's centre line along each beam
    # Within the barrier's half-width plus a cell's half-diagonal of the line, measured along the beam; a
    # beam slipping through between cells would read metres more.
    assert np.all(np.abs(ranges - expected) <= 0.075 / np.cos(scanner.angles))


def test_noise_free_endpoints_lie_on_occupied_cells():
    scene = small_floor()
    occ = rasterise_map(scene)
    scanner = _exact(laser_world_grid(scene))
    poses = np.array([[1.0, 1.5, 0.0], [4.3, 2.1, 2.0], [11.2, 0.6, -2.5], [2.2, 5.0, 1.0], [8.7, 4.1, -0.4]])
    ranges = scanner.cast_many(poses, noisy=False)
    assert ranges.dtype == np.float32 and ranges.shape == (5, 1081)
    args = (occ, poses, ranges, scanner.angle_min, scanner.angle_increment, scanner.range_max)
    assert endpoint_occupied_share(*args, tolerance_cells=1) == 1.0
    assert endpoint_occupied_share(*args, tolerance_cells=0) >= 0.999  # exact up to float32 rounding
    assert np.all(ranges < scanner.range_max)  # a closed floor: every beam returns


@pytest.mark.parametrize("pose", [(2.3, 1.7, 0.4), (0.5, 0.5, -2.0), (5.5, 3.2, 3.1), (3.0, 2.0, 0.0)])
def test_ranges_match_the_closed_form_in_a_rectangular_room(pose):
    scanner = _exact(rasterise_map(box_room()))
    ranges = scanner.cast(np.array(pose), noisy=False)
    np.testing.assert_allclose(ranges, _box_distances(np.array(pose), scanner.angles), atol=3e-4)


def test_beams_beyond_range_max_and_out_of_the_building_are_no_returns():
    scanner = _exact(rasterise_map(box_room()), range_max=2.0)
    pose = np.array([2.3, 1.7, 0.4])
    ranges = scanner.cast(pose, noisy=False)
    expected = _box_distances(pose, scanner.angles)
    far = expected > 2.0 + 1e-3
    assert far.any() and (~far).any()
    assert np.all(ranges[far] == np.float32(2.0))
    np.testing.assert_allclose(ranges[~far], expected[~far], atol=3e-4)
    # Through an open doorway in the outer wall nothing is hit before the grid ends: exactly range_max.
    scanner = _exact(rasterise_map(box_room(doorway=(1.0, 3.0))))
    ranges = scanner.cast(np.array([3.0, 2.0, 0.0]), noisy=False)
    ahead = np.abs(scanner.angles) < 0.2
    assert np.all(ranges[ahead] == np.float32(30.0))
    assert np.all(ranges[np.abs(scanner.angles) > 0.9] < 30.0)


def test_beam_angles_follow_the_site_yaml_convention():
    laser = Laser()
    scanner = LaserScanner(rasterise_map(box_room()))
    assert scanner.angles.size == laser.beams == 1081
    assert scanner.angle_min == pytest.approx(laser.angle_min)
    assert scanner.angle_increment == pytest.approx(laser.angle_increment)
    assert scanner.angles[-1] == pytest.approx(math.radians(laser.angle_max_deg))
    # Beam i points at pose yaw + angle_i: the beam along the robot's heading sees the east wall.
    mid = LaserScanner(rasterise_map(box_room()), beams=3, fov_deg=180.0, noise_sigma=0.0, dropout=0.0)
    np.testing.assert_allclose(mid.cast(np.array([2.0, 2.0, 0.0]), noisy=False), [1.9, 3.9, 1.9], atol=3e-4)


def test_noise_dropouts_and_determinism():
    world = rasterise_map(box_room())
    pose = np.array([2.3, 1.7, 0.4])
    exact = _exact(world).cast(pose, noisy=False)
    scans = LaserScanner(world, noise_sigma=0.01, dropout=0.05, seed=7).cast_many(np.repeat(pose[None], 40, 0))
    dropped = scans == np.float32(30.0)
    assert 0.03 < dropped.mean() < 0.07
    err = (scans - exact)[~dropped]
    assert abs(err.mean()) < 2e-3 and 0.008 < err.std() < 0.012
    again = LaserScanner(world, noise_sigma=0.01, dropout=0.05, seed=7).cast_many(np.repeat(pose[None], 40, 0))
    other = LaserScanner(world, noise_sigma=0.01, dropout=0.05, seed=8).cast_many(np.repeat(pose[None], 40, 0))
    assert np.array_equal(scans, again) and not np.array_equal(scans, other)


def test_people_discs_are_intersected_analytically():
    scanner = _exact(rasterise_map(box_room()), beams=181, fov_deg=180.0)
    pose = np.array([1.0, 2.0, 0.0])
    person = np.array([[3.0, 2.0, 0.25]])
    ranges = scanner.cast(pose, discs=person, noisy=False)
    assert ranges[90] == pytest.approx(1.75, abs=1e-5)  # straight ahead: centre distance minus radius
    assert ranges[0] == pytest.approx(1.9, abs=3e-4)  # to the right: the wall
    # A disc around the laser itself is ignored; per-pose discs (N, K, 3) are accepted.
    around = scanner.cast(pose, discs=np.array([[1.0, 2.0, 0.3]]), noisy=False)
    np.testing.assert_allclose(around, scanner.cast(pose, noisy=False))
    both = scanner.cast_many(np.stack([pose, pose]), discs=np.stack([person, person + [[0.0, 9.0, 0.0]]]),
                             noisy=False)
    assert both[0, 90] == pytest.approx(1.75, abs=1e-5) and both[1, 90] == pytest.approx(4.9, abs=3e-4)


def test_laser_inside_an_obstacle_reads_zero():
    scanner = _exact(rasterise_map(box_room()))
    assert np.all(scanner.cast(np.array([0.0, 2.0, 0.0]), noisy=False) == 0.0)


def test_laser_world_adds_unmapped_obstacles_and_removes_moved_objects():
    scene = small_floor()
    occ = rasterise_map(scene)
    world = laser_world_grid(scene, extra_discs=[(4.0, 1.5, 0.25)], extra_rects=[(9.0, 5.0, 0.5, 0.5, 0.52)],
                             removed_ids=[CHAIR.instance_id])
    assert occ.value_at(4.0, 1.5) == FREE and world.value_at(4.0, 1.5) == OCCUPIED
    assert occ.value_at(9.0, 5.0) == FREE and world.value_at(9.0, 5.0) == OCCUPIED
    assert occ.value_at(CHAIR.x, CHAIR.y) == OCCUPIED and world.value_at(CHAIR.x, CHAIR.y) != OCCUPIED
    assert world.value_at(CORE_CABINET.x, CORE_CABINET.y) == OCCUPIED  # real, only unmapped
    assert world.value_at(DESK.x, DESK.y) == OCCUPIED


def test_displaced_furniture_and_walking_people_stay_in_free_space():
    scene = small_floor()
    scene.objects.extend(
        SceneObject(10 + k, "chair", "chair", 1.0 + 0.8 * k, 4.0, 0.0, 0.0, (0.5, 0.52, 0.9), 0, True, "A")
        for k in range(5)
    )
    occ = rasterise_map(scene)
    rects, removed = displace_furniture(scene, occ, share=1.0, seed=3)
    assert len(rects) == len(removed) >= 4
    by_id = {o.instance_id: o for o in scene.objects}
    for (x, y, *_), i in zip(rects, removed, strict=True):
        assert 0.3 <= math.hypot(x - by_id[i].x, y - by_id[i].y) <= 1.0
        assert occ.value_at(x, y) == FREE
    robot = np.column_stack([np.linspace(1.0, 11.0, 30), np.full(30, 1.5)])
    people = walking_people(occ.free, occ, n_people=3, steps=30, seed=1, robot_xy=robot)
    assert people.shape == (30, 3, 3)
    assert np.all(occ.value_at(people[..., 0], people[..., 1]) == FREE)
    assert np.all((people[..., 2] >= 0.2) & (people[..., 2] <= 0.3))
    assert np.ptp(people[:, :, :2], axis=0).max() > 0.5  # they walk
    again = walking_people(occ.free, occ, n_people=3, steps=30, seed=1, robot_xy=robot)
    assert np.array_equal(people, again)


def test_laser_poses_apply_the_mount():
    base = np.array([[1.0, 2.0, math.pi / 2]])
    np.testing.assert_allclose(laser_poses(base, (0.2, 0.0, 0.1)), [[1.0, 2.2, math.pi / 2 + 0.1]], atol=1e-12)


def test_a_bare_room_without_objects_rasterises_and_scans():
    walls = [Wall(0, 0, 4, 0, 0.2, 2.5, 0), Wall(4, 0, 4, 3, 0.2, 2.5, 0), Wall(4, 3, 0, 3, 0.2, 2.5, 0),
             Wall(0, 3, 0, 0, 0.2, 2.5, 0)]
    scene = Scene("bare", 0, Rect(0, 0, 4, 3), walls, [Room("r", "office", Rect(0, 0, 4, 3), (), 0)], [], [], 2.5, ())
    scanner = _exact(rasterise_map(scene))
    ranges = scanner.cast(np.array([2.0, 1.5, 0.0]), noisy=False)
    assert ranges[540] == pytest.approx(1.9, abs=3e-4)
