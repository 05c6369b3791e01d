"""Camera hypotheses weighed against the tracked estimate (`pipeline.runtime.hypotheses`)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import FilterConfig
from pipeline.io.map_yaml import OccupancyMap
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.hypotheses import Hypotheses, Weighing, rank_near
from pipeline.runtime.motion import compose_odometry, odometry_delta
from pipeline.runtime.sensor import Scan, make_sensor_model
from pipeline.sitegen.laser import LaserScanner

RANGE_MAX = 20.0
RES = 0.05
SHIFT = 99 * RES  # room B is room A moved this far along x, cell for cell


@pytest.fixture(scope="module")
def twin_rooms():
    """Two identical rooms side by side (a wall between them, a cabinet and a pillar in each): a scan
    taken in one fits the same pose in the other exactly as well, the laser's quasi-symmetric floor in
    its purest form."""
    grid = np.zeros((100, 200), dtype=np.int8)
    grid[:2, :] = grid[-2:, :] = 100
    grid[:, :2] = grid[:, 99:101] = grid[:, 198:] = 100
    for x0 in (0, 99):  # the same furniture, cell for cell
        grid[30:50, x0 + 30:x0 + 40] = 100
        grid[70:74, x0 + 70:x0 + 74] = 100
    occ = OccupancyMap(grid, RES)
    cfg = FilterConfig()
    lmap = LaserMap.from_occupancy(occ, cfg.sensor.max_distance)
    beam = cfg.sensor.model_copy(update={"model": "beam", "beam_skip": False})
    sensor = make_sensor_model(lmap, beam, RANGE_MAX)
    scanner = LaserScanner(occ, beams=181, fov_deg=270, range_max=RANGE_MAX, noise_sigma=0.01, dropout=0.0, seed=2)
    return lmap, sensor, scanner


def scan_at(scanner, pose) -> Scan:
    ranges = scanner.cast_many(np.asarray(pose, dtype=np.float64)[None])[0]
    return Scan(ranges, scanner.angle_min, scanner.angle_increment, RANGE_MAX)


def how(**over) -> Weighing:
    kw = dict(pool=5, samples=128, rounds=4, std_xy=0.5, std_theta=np.radians(15), min_distance_m=3.0, distinct=0.1,
              laser_nats=3.0, min_fit=0.5, radius_m=1.0, heading_rad=np.radians(45), max_rank=None, min_checks=1)
    return Weighing(**{**kw, **over})


def test_rank_near_matches_a_loop_over_the_ranked_list():
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.uniform(0, 10, (300, 2)), rng.uniform(-np.pi, np.pi, 300)])
    ranked = np.column_stack([rng.uniform(0, 10, (40, 2)), rng.uniform(-np.pi, np.pi, 40)])
    got = rank_near(poses, ranked, radius_m=1.5, heading_rad=np.radians(50))
    for pose, r in zip(poses, got, strict=True):
        want = len(ranked)
        for k, q in enumerate(ranked):
            dh = abs((pose[2] - q[2] + np.pi) % (2 * np.pi) - np.pi)
            if np.hypot(*(pose[:2] - q[:2])) <= 1.5 and dh <= np.radians(50):
                want = k
                break
        assert r == want
    assert rank_near(poses[:3], np.zeros((0, 3)), radius_m=1.0, heading_rad=1.0).tolist() == [0, 0, 0]


def test_the_laser_cannot_tell_the_twin_rooms_apart(twin_rooms):
    lmap, sensor, scanner = twin_rooms
    truth = np.array([1.2, 2.6, 0.4])
    twin = truth + [SHIFT, 0.0, 0.0]
    ll = sensor.evaluate(np.vstack([truth, twin]), scan_at(scanner, truth)).log_likelihood
    assert ll[0] == pytest.approx(ll[1], abs=1e-6)


def test_a_twin_is_replaced_once_the_image_has_preferred_the_truth_long_enough(twin_rooms):
    """The truth's view is retrieved first, the believed twin's fifth: each check adds log(1 + 5) -
    log(1 + 0) to the truth's evidence; it wins at the first check at which both the threshold and
    min_checks are reached, not before."""
    lmap, sensor, scanner = twin_rooms
    truth = np.array([1.2, 2.6, 0.4])
    believed = truth + [SHIFT, 0.0, 0.0]  # the filter tracks the twin
    decoys = np.array([[3.0, 1.0, 2.0], [7.9, 1.0, -2.0], [2.0, 4.2, 1.0], [8.0, 4.2, 0.0]])
    ev = Hypotheses()
    odom = np.zeros(3)
    step = np.array([0.15, 0.0, 0.05])
    gain = np.log(6.0)
    threshold = 2.5 * gain
    for k in range(1, 5):
        ev.follow(odom, believed, tracking=True, jump_m=3.0)
        retrieved = np.vstack([truth + [0.2, -0.15, 0.1], decoys, believed + [0.1, 0.1, -0.05]])
        won = ev.check(sensor, lmap, believed, retrieved, scan_at(scanner, truth), how(min_checks=2),
                       threshold=threshold, rng=np.random.default_rng(k))
        if k < 3:
            assert won is None
            i = int(np.argmin(np.hypot(*(ev.poses[:, :2] - truth[:2]).T)))
            assert np.hypot(*(ev.poses[i, :2] - truth[:2])) < 0.3
            assert ev.evidence[i] == pytest.approx(k * gain) and ev.checks[i] == k
            # Decoys that do not fit the scan are not followed.
            assert all(np.hypot(*(p[:2] - d[:2])) > 0.5 for p in ev.poses for d in decoys)
        else:
            assert won is not None and np.hypot(*(won[:2] - truth[:2])) < 0.3
            assert len(ev.poses) == 0  # cleared: the belief is about to be replaced
            break
        new = compose_odometry(odom, *odometry_delta(np.zeros(3), step))
        truth = compose_odometry(truth, *odometry_delta(odom, new))
        believed = compose_odometry(believed, *odometry_delta(odom, new))
        decoys = compose_odometry(decoys, *odometry_delta(odom, new))
        odom = new
    assert k == 3


def test_the_truth_is_left_alone_when_the_image_prefers_it(twin_rooms):
    """Estimate right, its twin retrieved fifth: the twin fits the scan as well but the image's ratio
    for it is negative, so it is not followed; a twin whose view is retrieved first once gains one
    check's worth and loses it at the next."""
    lmap, sensor, scanner = twin_rooms
    truth = np.array([1.2, 2.6, 0.4])
    twin = truth + [SHIFT, 0.0, 0.0]
    scan = scan_at(scanner, truth)
    filler = np.array([[3.0, 1.0, 2.0], [7.9, 1.0, -2.0], [2.0, 4.2, 1.0], [8.0, 4.2, 0.0]])
    ev = Hypotheses()
    for k in range(4):
        won = ev.check(sensor, lmap, truth, np.vstack([truth, filler, twin]), scan, how(), threshold=3.0,
                       rng=np.random.default_rng(k))
        assert won is None and len(ev.poses) == 0
    ev.check(sensor, lmap, truth, np.vstack([twin, truth, filler]), scan, how(), threshold=3.0,
             rng=np.random.default_rng(9))
    assert len(ev.poses) == 1 and ev.evidence[0] == pytest.approx(np.log(2.0))
    ev.check(sensor, lmap, truth, np.vstack([truth, filler, twin]), scan, how(), threshold=3.0,
             rng=np.random.default_rng(10))
    assert len(ev.poses) == 0


def test_a_view_missed_by_retrieval_counts_as_max_rank(twin_rooms):
    lmap, sensor, scanner = twin_rooms
    truth = np.array([1.2, 2.6, 0.4])
    believed = truth + [SHIFT, 0.0, 0.0]
    retrieved = np.vstack([truth, [[3.0, 1.0, 2.0]] * 9])  # the believed place's views are not among ten
    for max_rank, want in ((None, np.log1p(10)), (4, np.log1p(4))):
        ev = Hypotheses()
        ev.check(sensor, lmap, believed, retrieved, scan_at(scanner, truth), how(max_rank=max_rank),
                 threshold=100.0, rng=np.random.default_rng(0))
        assert len(ev.poses) == 1 and ev.evidence[0] == pytest.approx(want)


def test_a_pose_the_laser_prefers_adds_laser_nats_and_one_it_rules_out_is_dropped(twin_rooms):
    """The estimate in the other room, off the scan: the truth fits better by more than `distinct` per
    beam and gains laser_nats beside the camera's ratio at each check; the same pose as the estimate,
    with the scan taken at the wrong place, fits worse and is not followed."""
    lmap, sensor, scanner = twin_rooms
    truth = np.array([1.2, 2.6, 0.4])
    believed = np.array([3.6 + SHIFT, 2.4, -1.2])  # the other room, another corner: the scan does not fit it
    scan = scan_at(scanner, truth)
    ll = sensor.evaluate(np.vstack([truth, believed]), scan).log_likelihood
    assert (ll[0] - ll[1]) / sensor.beams(scan)[0].size > 0.1
    ranked = np.vstack([truth, [[3.0, 1.0, 2.0]] * 4])  # the believed place's views are not among five
    for laser_nats in (0.0, 3.0):
        ev = Hypotheses()
        for k in (1, 2):
            ev.check(sensor, lmap, believed, ranked, scan, how(laser_nats=laser_nats), threshold=100.0,
                     rng=np.random.default_rng(k))
            assert len(ev.poses) == 1 and np.hypot(*(ev.poses[0, :2] - truth[:2])) < 0.3
            assert ev.evidence[0] == pytest.approx(k * (np.log1p(5) + laser_nats))
    # Roles swapped: the scan taken at `believed`, the estimate at the truth's twin fitting it: the truth
    # fits worse by far and is dropped whatever the camera says.
    ev = Hypotheses()
    ev.check(sensor, lmap, believed, ranked, scan_at(scanner, believed), how(), threshold=100.0,
             rng=np.random.default_rng(0))
    assert len(ev.poses) == 0


def test_the_belief_ages_while_tracked_without_a_jump():
    ev = Hypotheses()
    odom, pose = np.zeros(3), np.array([1.0, 1.0, 0.3])
    step = np.array([0.2, 0.0, 0.1])
    ages = []
    for k in range(8):
        jump = k == 5
        tracking = k != 2
        ev.follow(odom, pose + ([4.0, 0.0, 0.0] if jump else 0.0), tracking=tracking, jump_m=3.0)
        ages.append(ev.age)
        if jump:
            pose = pose + [4.0, 0.0, 0.0]
        new = compose_odometry(odom, *odometry_delta(np.zeros(3), step))
        pose = compose_odometry(pose, *odometry_delta(odom, new))
        odom = new
    # 0 at the first estimate, 0 while relocalising (k = 2) and at the jump (k = 5), else one older.
    assert ages == [0, 1, 0, 1, 2, 0, 1, 2]
