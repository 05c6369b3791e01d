"""Odometry motion model: decomposition round trips, exactness without noise, and noise statistics."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.runtime.motion import (
    compose_odometry,
    motion_noise_std,
    odometry_delta,
    sample_motion_model_odometry,
    wrap_angle,
)


def se2(pose) -> np.ndarray:
    """Homogeneous 3x3 matrix of a pose: an independent way to compose poses."""
    x, y, t = pose
    return np.array([[np.cos(t), -np.sin(t), x], [np.sin(t), np.cos(t), y], [0, 0, 1]])


def pose_of(m: np.ndarray) -> np.ndarray:
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])


def angle_close(a, b, atol=1e-9) -> bool:
    return bool(np.all(np.abs(wrap_angle(np.asarray(a) - np.asarray(b))) < atol))


coord = st.floats(-50, 50, allow_nan=False)
angle = st.floats(-10, 10, allow_nan=False)
poses = st.tuples(coord, coord, angle).map(np.array)


def test_wrap_angle_range_and_identity():
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert (w >= -np.pi).all() and (w < np.pi).all()
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)


def test_wrap_angle_never_returns_plus_pi():
    a = np.array([np.pi, -np.pi, 3 * np.pi, -np.pi - 1e-17, np.nextafter(-np.pi, -4), 0.1 - 1.0 - (np.pi - 0.9)])
    w = wrap_angle(a)
    assert np.all(w < np.pi) and np.all(w >= -np.pi)
    assert float(wrap_angle(np.pi)) == -np.pi


def test_known_decomposition():
    rot1, trans, rot2 = odometry_delta(np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, np.pi / 2]))
    assert (rot1, trans, rot2) == pytest.approx((np.pi / 4, np.sqrt(2), np.pi / 4))
    # Turning on the spot: no translation, so rot1 = 0 and the whole turn is rot2.
    rot1, trans, rot2 = odometry_delta(np.array([2.0, 3.0, 3.0]), np.array([2.0, 3.0, -3.0]))
    assert (rot1, trans) == (0.0, 0.0) and rot2 == pytest.approx(wrap_angle(-6.0))


@settings(max_examples=300, deadline=None)
@given(poses, poses)
def test_delta_compose_round_trip(prev, cur):
    rot1, trans, rot2 = odometry_delta(prev, cur)
    assert trans >= 0 and -np.pi <= rot1 < np.pi and -np.pi <= rot2 < np.pi
    back = compose_odometry(prev, rot1, trans, rot2)
    # Below min_trans (1e-9) rot1 is forced to 0, so the position can be off by at most 2 * trans.
    np.testing.assert_allclose(back[:2], cur[:2], atol=2e-9 + 1e-12)
    assert angle_close(back[2], cur[2])


@settings(max_examples=100, deadline=None)
@given(poses, poses, st.lists(poses, min_size=1, max_size=5))
def test_zero_noise_moves_every_particle_by_the_odometry(odom_prev, odom_cur, particle_list):
    """With alpha = 0 each particle moves by exactly inv(odom_prev) * odom_cur in its own frame (SE(2))."""
    particles = np.stack(particle_list)
    rng = np.random.default_rng(0)
    moved = sample_motion_model_odometry(particles, odom_prev, odom_cur, np.zeros(4), rng, min_trans=0.0)
    rel = np.linalg.inv(se2(odom_prev)) @ se2(odom_cur)
    for p, m in zip(particles, moved, strict=True):
        expected = pose_of(se2(p) @ rel)
        np.testing.assert_allclose(m[:2], expected[:2], atol=1e-8)
        assert angle_close(m[2], expected[2], 1e-8)


def test_vectorised_over_leading_axes():
    prev = np.random.default_rng(1).normal(size=(4, 5, 3))
    cur = np.random.default_rng(2).normal(size=(4, 5, 3))
    rot1, trans, rot2 = odometry_delta(prev, cur)
    assert rot1.shape == trans.shape == rot2.shape == (4, 5)
    np.testing.assert_allclose(compose_odometry(prev, rot1, trans, rot2)[..., :2], cur[..., :2], atol=1e-12)


def test_sample_statistics_match_the_closed_form():
    """Table 5.6: each noisy component is normal around the odometry's with std sqrt(a_i x^2 + a_j y^2)."""
    # alpha3 small enough that no sampled translation is negative (6 sigma), or recovering the samples
    # from the moved particles below would read them as forwards with rot1 + pi.
    alpha = np.array([0.05, 0.02, 0.02, 0.03])
    odom_prev, odom_cur = np.array([1.0, 2.0, 0.3]), np.array([1.6, 2.9, 0.5])
    d = odometry_delta(odom_prev, odom_cur)
    expected_std = motion_noise_std(*d, alpha)
    # By hand from the table, as a check of motion_noise_std itself.
    r1, tr, r2 = (float(v) for v in d)
    hand = (
        np.sqrt(0.05 * r1**2 + 0.02 * tr**2),
        np.sqrt(0.02 * tr**2 + 0.03 * r1**2 + 0.03 * r2**2),
        np.sqrt(0.05 * r2**2 + 0.02 * tr**2),
    )
    np.testing.assert_allclose(expected_std, hand)

    n = 200_000
    start = np.zeros((n, 3))
    moved = sample_motion_model_odometry(start, odom_prev, odom_cur, alpha, np.random.default_rng(7))
    got = odometry_delta(start, moved)  # recover each particle's sampled (rot1, trans, rot2)
    for sample, mean, std in zip(got, d, expected_std, strict=True):
        # Mean within 4 standard errors; std within 1.5 % (its standard error is ~0.16 % here).
        assert abs(sample.mean() - mean) < 4 * std / np.sqrt(n)
        assert sample.std() == pytest.approx(std, rel=0.015)


def test_backward_motion_noise_is_small_like_nav2():
    """Reversing 0.5 m gives rot1 ~ pi, but its noise is scaled by the turn from straight back (0), not pi."""
    alpha = np.array([0.2, 0.02, 0.1, 0.05])
    odom_prev, odom_cur = np.array([0.0, 0.0, 0.0]), np.array([-0.5, 0.0, 0.0])
    rot1, trans, rot2 = odometry_delta(odom_prev, odom_cur)
    assert abs(rot1) == pytest.approx(np.pi)
    s1, _, _ = motion_noise_std(rot1, trans, rot2, alpha)
    assert s1 == pytest.approx(np.sqrt(0.02) * 0.5)
    moved = sample_motion_model_odometry(np.zeros((20_000, 3)), odom_prev, odom_cur, alpha, np.random.default_rng(3))
    assert moved[:, 0].mean() == pytest.approx(-0.5, abs=0.01)  # the particles do move backwards


def test_seeded_and_input_untouched():
    particles = np.random.default_rng(5).normal(size=(100, 3))
    copy = particles.copy()
    args = (np.array([0.0, 0.0, 0.0]), np.array([0.4, 0.1, 0.2]), np.full(4, 0.1))
    a = sample_motion_model_odometry(particles, *args, np.random.default_rng(11))
    b = sample_motion_model_odometry(particles, *args, np.random.default_rng(11))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(particles, copy)
    assert not np.allclose(a, sample_motion_model_odometry(particles, *args, np.random.default_rng(12)))


def test_runtime_does_not_import_torch():
    code = ("import sys, pipeline.runtime.motion, pipeline.runtime.amcl, pipeline.runtime.kernels; "
            "assert not {'torch', 'torchvision', 'cv2'} & set(sys.modules), 'a heavy module was imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
