"""The camera path (`pipeline.runtime.camera`): a kidnapping the camera proposes is caught while tracking."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import FilterConfig
from pipeline.runtime.amcl import AdaptiveMCL, FilterState
from pipeline.runtime.camera import CameraPath
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.motion import compose_odometry, odometry_delta
from pipeline.runtime.sensor import Scan
from pipeline.sitegen.laser import LaserScanner, rasterise_map
from pipeline.sitegen.trajectories import sample_stops
from tests.sitegen.small_floor import small_floor

RANGE_MAX = 30.0


@pytest.fixture(scope="module")
def floor():
    scene = small_floor()
    occ = rasterise_map(scene)
    lmap = LaserMap.from_occupancy(occ, FilterConfig().sensor.max_distance)
    scanner = LaserScanner(occ, beams=181, fov_deg=270, range_max=RANGE_MAX, seed=1)
    stops = np.array([s[:2] for s in sample_stops(scene, occ, spacing=2.0, clearance=0.45, jitter=0.3, seed=4)])
    return lmap, scanner, stops


def kidnapped_replay(floor, cfg: FilterConfig, steps: int = 14):
    """Tracking from the truth at stop 3 for 4 steps, then teleported to a stop over 5 m away while the
    odometry carries on; a simulated camera ranks the truth (with noise) second among three free-space
    decoys at every step. Returns the position error and the camera path's source per step."""
    lmap, scanner, stops = floor
    start = np.array([*stops[3], 0.3])
    there = next(p for p in stops if np.hypot(*(p - stops[3])) > 5.0)
    rng = np.random.default_rng(5)
    truth, odom = start.copy(), np.zeros(3)
    move = np.array([0.25, 0.0, 0.05])  # in the robot's frame

    def rank(t):
        decoys = lmap.sample_free(3, rng)
        return np.vstack([decoys[:1], truth + rng.normal(0, [0.3, 0.3, 0.1]), decoys[1:]])

    f = AdaptiveMCL(lmap, cfg, range_max=RANGE_MAX)
    camera = CameraPath(f, cfg, (4.0, 3.0, 2.0, 1.0), rank_image=rank, range_max=RANGE_MAX)
    f.init_pose(start)
    camera.started = camera.seeded_by_camera = True
    errors, sources = [], []
    for t in range(steps):
        new = compose_odometry(odom, *odometry_delta(np.zeros(3), move))
        truth = compose_odometry(truth, *odometry_delta(odom, new))
        if t == 4:
            truth = np.array([*there, truth[2] + 1.0])
        odom = new
        ranges = scanner.cast_many(truth[None])[0]
        got = camera.step(odom, Scan(ranges, scanner.angle_min, scanner.angle_increment, RANGE_MAX), t)
        errors.append(float(np.hypot(*(got.result.pose[:2] - truth[:2]))))
        sources.append(got.source)
    return np.array(errors), sources, f


def test_a_kidnapping_the_camera_sees_is_caught_before_the_kidnap_rule_fires(floor):
    """With the laser's kidnap rule off, the camera path alone brings the filter to the new place: the
    truth is proposed, fits the scan better than the estimate by far, and wins after min_checks checks,
    replacing the belief. With the camera's weighing off, nothing does."""
    base = FilterConfig(min_particles=300, max_particles=2000)
    no_rule = base.model_copy(update={"kidnap": base.kidnap.model_copy(update={"updates": 10_000})})
    errors, sources, f = kidnapped_replay(floor, no_rule)
    assert np.all(errors[:4] < 0.3)
    won = sources.index("hypothesis")
    assert won == 4 + no_rule.camera.min_checks - 1  # the kidnapping at 4, then min_checks checks
    assert np.all(errors[won:] < 0.5) and f.state == FilterState.TRACKING

    off = no_rule.model_copy(update={"camera": no_rule.camera.model_copy(update={"every": 0})})
    errors, sources, _ = kidnapped_replay(floor, off)
    assert "hypothesis" not in sources and np.all(errors[4:] > 2.0)
