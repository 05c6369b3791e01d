"""TUM trajectory files and evo's APE / RPE, against our own metrics and closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.metrics import replay_metrics
from pipeline.evaluation.trajectories import evo_metrics, step_stamps, write_tum


def _loop(n=200):
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([10 * np.cos(s), 6 * np.sin(s), np.arctan2(6 * np.cos(s), -10 * np.sin(s))])


def test_tum_files_round_trip_through_evos_reader(tmp_path):
    from evo.tools.file_interface import read_tum_trajectory_file

    gt = _loop()
    stamps = 100.0 + 0.1 * np.arange(len(gt))
    path = write_tum(tmp_path / "run_groundtruth.tum", gt, stamps)
    back = read_tum_trajectory_file(path)
    np.testing.assert_allclose(back.timestamps, stamps)
    np.testing.assert_allclose(back.positions_xyz[:, :2], gt[:, :2])
    np.testing.assert_allclose(back.positions_xyz[:, 2], 0.0)
    yaw = np.array([np.arctan2(R[1, 0], R[0, 0]) for R in (p[:3, :3] for p in back.poses_se3)])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - gt[:, 2]))), 0.0, atol=1e-9)
    assert not list(tmp_path.glob("*.tmp"))


def test_ape_equals_our_median_on_a_constant_offset():
    gt = _loop()
    est = gt + np.array([0.3, -0.4, 0.0])  # 0.5 m everywhere
    err = np.hypot(*(est[:, :2] - gt[:, :2]).T)
    ours = replay_metrics(err, [], np.ones(len(gt)), np.zeros(len(gt)), np.ones(len(gt), bool))
    m = evo_metrics(est, gt, np.arange(len(gt), dtype=float))
    assert m["ape_m"]["median"] == pytest.approx(ours["error_median_all_m"]) == pytest.approx(0.5)
    assert m["ape_m"]["rmse"] == pytest.approx(0.5)
    assert m["rpe_m"]["max"] == pytest.approx(0.0, abs=1e-9)  # a constant offset moves like the truth


def test_rpe_of_a_scaled_straight_run_is_the_scale_error_per_metre():
    gt = np.column_stack([np.arange(50) * 0.5, np.zeros(50), np.zeros(50)])  # 0.5 m steps along x
    est = gt * np.array([1.1, 1.0, 1.0])  # odometry 10 % long
    m = evo_metrics(est, gt, np.arange(50, dtype=float))
    assert m["rpe_m"]["median"] == pytest.approx(0.1)  # 10 cm over each metre travelled
    assert m["rpe_deg"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert evo_metrics(est[:3], gt[:3], np.arange(3.0))["rpe_m"] is None  # under 2 m travelled: no RPE


def test_stamps_fall_back_to_steps_when_not_increasing():
    np.testing.assert_array_equal(step_stamps(np.array([1.0, 1.0, 2.0]), 3), [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(step_stamps(np.array([1.0, 2.0, 3.5]), 3), [1.0, 2.0, 3.5])
    np.testing.assert_array_equal(step_stamps(None, 2), [0.0, 1.0])
