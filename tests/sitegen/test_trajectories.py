"""Capture stops, routes and simulated runs on a small hand-built floor: clearance, spacing, kidnappings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.config import OdometryNoise
from pipeline.errors import Problems
from pipeline.io.capture_runs import read_run
from pipeline.io.map_yaml import FREE
from pipeline.io.odometry import noise_alphas, relative_to_first
from pipeline.runtime.motion import motion_noise_std, odometry_delta, wrap_angle
from pipeline.sitegen.laser import LaserScanner, laser_world_grid, rasterise_map
from pipeline.sitegen.routes import RoutePlanner, clearance_field
from pipeline.sitegen.trajectories import RIG_OFFSETS, make_runs, plan_route, sample_stops, write_capture_run
from tests.sitegen.small_floor import small_floor

STEP = 0.4


@pytest.fixture(scope="module")
def floor():
    scene = small_floor()
    return scene, rasterise_map(scene)


@pytest.fixture(scope="module")
def stops(floor):
    return sample_stops(*floor, spacing=2.0, clearance=0.45, jitter=0.3, seed=4)


@pytest.fixture(scope="module")
def runs(floor, stops):
    return make_runs(*floor, stops, n_mapping=1, n_query=2, steps_per_run=60, step=STEP, kidnaps_per_query_run=2,
                     seed=5)


def _clearance_at(occ, xy) -> np.ndarray:
    row, col = occ.world_to_cell(xy[:, 0], xy[:, 1])
    return clearance_field(occ)[row, col]


def test_stops_have_clearance_spacing_and_cover_every_room(floor, stops):
    scene, occ = floor
    xy = np.array(stops)[:, :2]
    assert len(stops) >= 10
    assert np.all(occ.value_at(xy[:, 0], xy[:, 1]) == FREE)
    assert np.all(_clearance_at(occ, xy) >= 0.45)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    assert nearest.min() >= 0.6 * 2.0 and 0.7 * 2.0 <= np.median(nearest) <= 1.2 * 2.0
    for room in scene.rooms:
        assert any(room.rect.contains(x, y) for x, y in xy), room.name
    assert not any(scene.closed[0].contains(x, y) for x, y in xy)
    headings = np.array(stops)[:, 2]
    assert np.all((headings >= -math.pi) & (headings < math.pi)) and np.std(headings) > 1.0


def test_stops_are_deterministic_for_a_seed(floor, stops):
    assert sample_stops(*floor, seed=4) == stops
    assert sample_stops(*floor, seed=5) != stops


def test_route_stays_clear_with_requested_steps_and_heading_along_the_path(floor):
    _, occ = floor
    waypoints = [(1.0, 1.5), (2.5, 5.0), (11.0, 0.8), (8.0, 4.5)]  # corridor -> room A -> corridor -> room B
    route = plan_route(occ, waypoints, clearance=0.3, step=STEP, seed=1)
    assert route.shape[1] == 3 and len(route) > 50
    assert np.all(occ.value_at(route[:, 0], route[:, 1]) == FREE)
    assert np.all(_clearance_at(occ, route[:, :2]) >= 0.3 - occ.resolution)
    steps = np.hypot(*np.diff(route[:, :2], axis=0).T)
    assert steps.max() <= STEP + 1e-9
    assert np.mean(np.abs(steps - STEP) < 1e-6) > 0.8  # shorter only where the path turns
    np.testing.assert_allclose(route[0, :2], waypoints[0])
    for w in waypoints[1:]:
        assert np.min(np.hypot(route[:, 0] - w[0], route[:, 1] - w[1])) <= STEP
    travel = np.arctan2(*np.diff(route[:, :2], axis=0).T[::-1])
    assert np.median(np.abs(wrap_angle(route[:-1, 2] - travel))) < math.radians(10)
    assert np.array_equal(route, plan_route(occ, waypoints, clearance=0.3, step=STEP, seed=1))


def test_route_into_unreachable_space_is_refused(floor):
    _, occ = floor
    planner = RoutePlanner(occ, clearance=0.3)
    with pytest.raises(ValueError, match="clearance"):
        planner.leg((1.0, 1.5), (11.0, 7.0))  # inside the closed core: unknown, not free
    with pytest.raises(ValueError, match="clearance"):
        planner.leg((1.0, 1.5), (1.0, 3.0))  # inside a wall


def test_runs_have_expected_kinds_shapes_and_clear_ground_truth(floor, runs):
    _, occ = floor
    assert [(r.name, r.kind) for r in runs] == [("mapping_00", "mapping"), ("query_00", "query"),
                                                 ("query_01", "query")]
    for r in runs:
        assert r.gt.shape == r.odom.shape == (60, 3) and r.kidnapped.shape == (60,) and r.t.shape == (60,)
        assert np.all(np.diff(r.t) > 0)
        assert np.all(_clearance_at(occ, r.gt[:, :2]) >= 0.3 - occ.resolution)
        np.testing.assert_array_equal(r.odom[0], 0.0)


def test_kidnap_flags_match_ground_truth_jumps(runs):
    for r in runs:
        jumps = np.r_[0.0, np.hypot(*np.diff(r.gt[:, :2], axis=0).T)]
        flagged = np.nonzero(r.kidnapped)[0]
        assert len(flagged) == (2 if r.kind == "query" else 0)
        assert not r.kidnapped[0]
        assert np.all(jumps[flagged] > 5.0)
        assert np.all(jumps[~r.kidnapped] <= 3 * STEP)


def test_odometry_follows_the_motion_made_not_the_jump(runs):
    for r in runs:
        rot1, trans, rot2 = odometry_delta(r.odom[:-1], r.odom[1:])
        gt_rot1, gt_trans, gt_rot2 = odometry_delta(r.gt[:-1], r.gt[1:])
        carried = r.kidnapped[1:]
        assert np.all(trans[carried] < 0.1) and np.all(np.abs(wrap_angle(rot1 + rot2))[carried] < 0.2)
        assert np.all(np.abs(trans - gt_trans)[~carried] < 0.05)  # the motion model's noise, a few cm per step
        # The heading error of a step is the sum of the rot1 and rot2 draws: bound it by 5 of their joint sigmas.
        s1, _, s2 = motion_noise_std(gt_rot1, gt_trans, gt_rot2, noise_alphas(OdometryNoise()))
        turn = wrap_angle((rot1 + rot2) - (gt_rot1 + gt_rot2))
        assert np.all(np.abs(turn[~carried]) < 5 * np.hypot(s1, s2)[~carried] + 1e-9)


def test_noise_free_odometry_is_the_ground_truth_until_the_first_kidnap(floor, stops):
    zero = OdometryNoise(alpha1=0, alpha2=0, alpha3=0, alpha4=0)
    runs = make_runs(*floor, stops, 1, 1, 40, STEP, 1, seed=2, noise=zero)
    mapping, query = runs
    np.testing.assert_allclose(mapping.odom, relative_to_first(mapping.gt), atol=1e-9)
    k = int(np.argmax(query.kidnapped))
    assert k > 0
    np.testing.assert_allclose(query.odom[:k], relative_to_first(query.gt[:k]), atol=1e-9)


def test_query_runs_look_where_the_stops_did_not(runs, stops):
    s = np.array(stops)

    def gap_deg(poses):
        near = np.argmin(np.hypot(poses[:, None, 0] - s[None, :, 0], poses[:, None, 1] - s[None, :, 1]), axis=1)
        seen = s[near, 2][:, None] + np.array(RIG_OFFSETS)[None, :]
        return np.degrees(np.abs(wrap_angle(poses[:, 2:3] - seen)).min(axis=1))

    query = np.vstack([r.gt for r in runs if r.kind == "query"])
    assert np.median(gap_deg(query)) > 20.0  # 15 for headings unrelated to the stops' views, 30 at most
    xy = query[:, :2]
    assert np.median(np.min(np.hypot(xy[:, None, 0] - s[None, :, 0], xy[:, None, 1] - s[None, :, 1]), axis=1)) > 0.2


def test_runs_are_deterministic_for_a_seed(floor, stops, runs):
    again = make_runs(*floor, stops, n_mapping=1, n_query=2, steps_per_run=60, step=STEP, kidnaps_per_query_run=2,
                      seed=5)
    for a, b in zip(runs, again, strict=True):
        assert np.array_equal(a.gt, b.gt) and np.array_equal(a.odom, b.odom)
        assert np.array_equal(a.kidnapped, b.kidnapped)
    other = make_runs(*floor, stops, 1, 2, 60, STEP, 2, seed=6)
    assert not np.array_equal(other[1].gt, runs[1].gt)


def test_written_run_reads_back_in_the_capture_format(tmp_path, floor, runs):
    scene, occ = floor
    run = runs[1]
    scanner = LaserScanner(laser_world_grid(scene), beams=181, seed=1)
    ranges = scanner.cast_many(run.gt)
    names = [f"images/runs/{run.name}/{i:04d}.jpg" if i % 3 == 0 else None for i in range(len(run.t))]
    for name in filter(None, names):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    run_dir = write_capture_run(tmp_path / "runs" / run.name, run, ranges, names)
    assert sorted(p.name for p in run_dir.iterdir()) == ["scans.npy", "trajectory.csv"]  # no temporaries left
    problems = Problems()
    back = read_run(run_dir, tmp_path, None, occ, problems)
    assert not problems, problems.items
    np.testing.assert_array_equal(back.t, run.t)
    np.testing.assert_array_equal(back.odom, run.odom)
    np.testing.assert_array_equal(back.gt, run.gt)
    np.testing.assert_array_equal(back.ranges, ranges)
    assert back.kidnapped == list(run.kidnapped) and back.image == names
    with pytest.raises(ValueError):
        write_capture_run(tmp_path / "bad", run, ranges[:-1], names)


def test_mapping_tours_go_by_driving_distance_and_pair_up_both_ways(floor, stops):
    from scipy.sparse.csgraph import dijkstra

    from pipeline.sitegen.routes import RoutePlanner
    from pipeline.sitegen.trajectories import _Driver

    planner = RoutePlanner(floor[1], 0.3)
    drv = _Driver(planner, np.asarray(stops, dtype=float), STEP, np.random.default_rng(0))
    xy = drv.stops[:, :2]
    nodes = np.array([planner.node(x, y) for x, y in xy])
    paths = dijkstra(planner.graph, indices=nodes)[:, nodes]  # every driving distance, unbounded
    straight = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.testing.assert_allclose(paths, paths.T, atol=1e-9)
    assert np.all(np.diag(paths) == 0) and np.all(paths >= straight - 0.3)  # planning cells are 0.1 m

    def order(tour):
        pts = [next(tour) for _ in range(len(xy))]
        return [int(np.argmin(np.hypot(*(xy - p).T))) for p in pts]

    fwd, back = order(drv.tour(0)), order(drv.tour(0, reverse=True))
    assert sorted(fwd) == list(range(len(xy)))
    for k in range(1, len(fwd)):  # greedy: each next stop is the nearest one left by driving distance
        left = [j for j in range(len(xy)) if j not in fwd[:k]]
        assert paths[fwd[k - 1], fwd[k]] == pytest.approx(min(paths[fwd[k - 1], j] for j in left))
    assert back == [fwd[0], *fwd[:0:-1]]

    runs = make_runs(*floor, stops, n_mapping=2, n_query=0, steps_per_run=20, mapping_steps=35, step=STEP, seed=1)
    assert [len(r.gt) for r in runs] == [35, 35]
    np.testing.assert_allclose(runs[0].gt[0, :2], runs[1].gt[0, :2])  # a pair starts at the same stop
    assert not np.allclose(runs[0].gt[5:, :2], runs[1].gt[5:, :2])  # and drives the other way round


def test_query_runs_do_not_depend_on_the_mapping_runs(floor, stops):
    a = make_runs(*floor, stops, n_mapping=1, n_query=1, steps_per_run=30, step=STEP, seed=3)
    b = make_runs(*floor, stops, n_mapping=2, n_query=1, steps_per_run=30, mapping_steps=50, step=STEP, seed=3)
    np.testing.assert_array_equal(a[-1].gt, b[-1].gt)
    np.testing.assert_array_equal(a[-1].odom, b[-1].odom)


def test_kidnappings_are_spread_at_least_half_a_bin_apart():
    from pipeline.sitegen.trajectories import _kidnap_steps

    for seed in range(200):
        steps = _kidnap_steps(200, 4, np.random.default_rng(seed))
        assert len(steps) == 4 and steps == sorted(steps)
        assert 40 <= steps[0] and steps[-1] < 197
        assert min(np.diff(steps)) >= (79 - 40) // 2  # half of a (197 - 40) / 4 bin
    assert _kidnap_steps(8, 2, np.random.default_rng(0)) == [] and _kidnap_steps(100, 0, np.random.default_rng(0)) == []
