"""Teleport kidnappings: ground truth jumps far, odometry carries on smoothly, scans follow the truth."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.evaluation.replay import ReplayRun, simulated_candidates, teleport
from pipeline.runtime.motion import odometry_delta


def line_run(n=200) -> ReplayRun:
    t = np.arange(n) * 0.3
    gt = np.column_stack([t, np.sin(t / 5), np.full(n, 0.2)])
    odom = gt + [1.0, -2.0, 0.0]  # another frame, same motion
    ranges = np.arange(n, dtype=np.float32)[:, None] * np.ones(5, np.float32)  # scan i "is" step i
    return ReplayRun("line", odom, gt, ranges, -1.0, 0.5, 30.0, np.zeros(n, bool))


def test_teleport_jumps_truth_not_odometry():
    run = line_run()
    k = teleport(run, [50, 120], min_jump_m=10.0, seed=3)
    assert len(k) == len(run) and np.nonzero(k.kidnapped)[0].tolist() == [50, 120]
    jumps = np.hypot(*np.diff(k.gt[:, :2], axis=0).T)
    assert jumps[49] >= 10 and jumps[119] >= 10
    assert np.all(np.delete(jumps, [49, 119]) < 0.35)
    src = k.ranges[:, 0].astype(int)  # which original step each replayed step is
    np.testing.assert_array_equal(k.gt, run.gt[src])
    _, trans, _ = odometry_delta(k.odom[:-1], k.odom[1:])
    _, gt_trans, _ = odometry_delta(k.gt[:-1], k.gt[1:])
    assert trans[49] == 0 and trans[119] == 0  # carried: the odometry saw nothing
    ok = np.ones(len(trans), bool)
    ok[[49, 119]] = False
    np.testing.assert_allclose(trans[ok], gt_trans[ok], atol=1e-9)
    np.testing.assert_array_equal(teleport(run, [50, 120], 10.0, seed=3).gt, k.gt)
    from dataclasses import replace

    framed = teleport(replace(run, image_ids=tuple(f"f{i}.png" for i in range(len(run)))), [50, 120], 10.0, seed=3)
    assert list(framed.image_ids) == [f"f{i}.png" for i in src]  # each step keeps the frame of its place


def test_teleport_refuses_what_it_cannot_do():
    run = line_run(30)
    with pytest.raises(ConfigError, match="outside run"):
        teleport(run, [30], 1.0, 0)
    with pytest.raises(ConfigError, match="kidnap-min-jump"):
        teleport(run, [10], 1000.0, 0)


def test_simulated_candidates_hold_the_truth_once():
    from pipeline.io.map_yaml import FREE, OccupancyMap
    from pipeline.runtime.grid import LaserMap

    grid = np.full((100, 100), FREE, np.int8)
    grid[0] = 100
    lmap = LaserMap.from_occupancy(OccupancyMap(grid, 0.1, 0.0, 0.0))
    rng = np.random.default_rng(0)
    ranks = []
    for _ in range(400):
        c = simulated_candidates(np.array([5.0, 5.0, 0.0]), lmap, 4, rng)
        d = np.hypot(c[:, 0] - 5, c[:, 1] - 5)
        ranks.append(int(np.argmin(d)))
    counts = np.bincount(ranks, minlength=4)
    assert counts.min() > 70  # the true one is at every rank about a quarter of the time
