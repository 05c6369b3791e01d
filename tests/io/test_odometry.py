"""Synthesised odometry: exact without noise, reproducible for a seed, noise as the motion model says."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import OdometryNoise
from pipeline.io.odometry import relative_to_first, synthesise_odometry
from pipeline.runtime.motion import odometry_delta, wrap_angle
from tests.runtime.test_motion import pose_of, se2

ZERO = OdometryNoise(alpha1=0, alpha2=0, alpha3=0, alpha4=0)


def _wiggly_path(n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(4)
    theta = np.cumsum(rng.normal(0, 0.3, n)) + 2.0
    step = rng.uniform(0.0, 0.8, n)
    step[::17] = 0.0  # turns on the spot
    x = 5 + np.cumsum(step * np.cos(theta))
    y = -3 + np.cumsum(step * np.sin(theta))
    return np.stack([x, y, wrap_angle(theta + rng.normal(0, 0.1, n))], axis=1)


def test_zero_noise_is_ground_truth_relative_to_its_start():
    gt = _wiggly_path()
    odom = synthesise_odometry(gt, ZERO, seed=0)
    first_inv = np.linalg.inv(se2(gt[0]))
    expected = np.stack([pose_of(first_inv @ se2(p)) for p in gt])  # SE(2) matrices, independent of the code
    np.testing.assert_allclose(odom[:, :2], expected[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(odom[:, 2] - expected[:, 2]), 0, atol=1e-9)
    np.testing.assert_allclose(relative_to_first(gt), odom, atol=1e-9)
    np.testing.assert_array_equal(odom[0], [0, 0, 0])


def test_seeded():
    gt, noise = _wiggly_path(), OdometryNoise()
    a, b = synthesise_odometry(gt, noise, seed=3), synthesise_odometry(gt, noise, seed=3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, synthesise_odometry(gt, noise, seed=4))


def test_step_noise_follows_the_motion_model():
    """Straight 0.5 m steps: odometry step lengths are N(0.5, a3 0.5^2), turns N(0, a2 0.5^2) each."""
    n = 20_001
    gt = np.zeros((n, 3))
    gt[:, 0] = 0.5 * np.arange(n)
    noise = OdometryNoise(alpha1=0.0, alpha2=0.01, alpha3=0.04, alpha4=0.0)
    odom = synthesise_odometry(gt, noise, seed=1)
    rot1, trans, rot2 = odometry_delta(odom[:-1], odom[1:])
    assert trans.std() == pytest.approx(np.sqrt(0.04) * 0.5, rel=0.03)
    assert trans.mean() == pytest.approx(0.5, abs=0.002)
    assert (rot1 + rot2).std() == pytest.approx(np.sqrt(2 * 0.01) * 0.5, rel=0.03)


def test_shapes():
    assert synthesise_odometry(np.zeros((1, 3)), OdometryNoise(), 0).shape == (1, 3)
    with pytest.raises(ValueError):
        synthesise_odometry(np.zeros((5, 2)), OdometryNoise(), 0)
