"""Cluster-based pose estimate: circular means, wrapped clusters, the heavier mode wins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.runtime.estimate import _mode_sums_numpy, cluster_labels, estimate_pose, mode_near_best, weighted_pose
from pipeline.runtime.sampling import pose_cells


def test_circular_mean_and_wrapped_covariance():
    poses = np.array([[0.0, 0.0, math.pi - 0.1], [2.0, 0.0, -math.pi + 0.1]])
    mean, cov = weighted_pose(poses, np.array([1.0, 1.0]))
    assert abs(abs(mean[2]) - math.pi) < 1e-9  # not 0, the naive mean of the two numbers
    assert mean[0] == pytest.approx(1.0) and cov[0, 0] == pytest.approx(1.0) and cov[2, 2] == pytest.approx(0.01)


def test_brute_force_covariance():
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.normal(3, 0.3, 400), rng.normal(-1, 0.2, 400), rng.normal(0.5, 0.1, 400)])
    w = rng.random(400)
    mean, cov = weighted_pose(poses, w)
    np.testing.assert_allclose(cov, np.cov(poses.T, aweights=w, bias=True), atol=1e-9)
    np.testing.assert_allclose(mean[:2], np.average(poses[:, :2], axis=0, weights=w))


def test_clusters_wrap_in_heading_and_split_in_space():
    rng = np.random.default_rng(1)
    around_pi = np.column_stack([rng.normal(1, 0.1, 200), rng.normal(1, 0.1, 200), rng.normal(math.pi, 0.05, 200)])
    around_pi[:, 2] = (around_pi[:, 2] + math.pi) % (2 * math.pi) - math.pi  # half near +pi, half near -pi
    far = np.column_stack([rng.normal(9, 0.1, 100), rng.normal(1, 0.1, 100), rng.normal(0, 0.05, 100)])
    labels, n = cluster_labels(np.vstack([around_pi, far]), 0.5, math.radians(10))
    assert n == 2 and len(set(labels[:200])) == 1 and len(set(labels[200:])) == 1


def test_the_heavier_mode_is_the_estimate_not_the_average():
    rng = np.random.default_rng(2)
    a = np.column_stack([rng.normal(2, 0.05, 300), rng.normal(2, 0.05, 300), rng.normal(0, 0.02, 300)])
    b = np.column_stack([rng.normal(12, 0.05, 200), rng.normal(2, 0.05, 200), rng.normal(0, 0.02, 200)])
    est = estimate_pose(np.vstack([a, b]), np.r_[np.full(300, 1.0), np.full(200, 2.0)])
    assert est.pose[0] == pytest.approx(12, abs=0.05) and est.clusters == 2
    assert est.cluster_weight == pytest.approx(400 / 700) and est.std_xy < 0.1


def test_compiled_labelling_matches_the_scipy_twin():
    from pipeline.runtime import estimate

    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(0, 6, 400), rng.uniform(0, 4, 400), rng.uniform(-math.pi, math.pi, 400)])
    poses = poses[(poses[:, 0] < 2) | (poses[:, 0] > 4) | (poses[:, 1] < 1)]  # a U shape: one or two blobs
    n_theta = 36
    cells = pose_cells(poses, 0.3, n_theta)
    base = cells.min(axis=0)
    span = cells.max(axis=0) - base + 3
    keys = ((cells[:, 0] - base[0] + 1) * span[1] + (cells[:, 1] - base[1] + 1)) * n_theta + cells[:, 2]
    uniq = np.unique(keys)
    fast, n_fast = estimate._label_sorted_keys(uniq, int(span[1]), n_theta)
    slow, n_slow = estimate._label_sorted_keys_scipy(uniq, int(span[1]), n_theta)
    assert n_fast == n_slow > 5  # sparse: many small clusters
    # The same partition, whatever the label numbers.
    pairs = set(zip(fast.tolist(), slow.tolist(), strict=True))
    assert len(pairs) == n_fast


def test_mode_near_best_is_the_weighted_mean_within_a_metre_of_the_heaviest_particle():
    rng = np.random.default_rng(6)
    near = np.column_stack([rng.normal(2.0, 0.2, 400), rng.normal(-1.0, 0.2, 400), rng.normal(3.1, 0.05, 400)])
    far = np.column_stack([rng.uniform(-20, 20, 600), rng.uniform(-20, 20, 600), rng.uniform(-3, 3, 600)])
    poses = np.vstack([near, far])
    w = rng.random(1000) * np.r_[np.full(400, 3.0), np.ones(600)]
    w[7] = 10.0  # the heaviest particle, one of the cluster
    log_w = np.log(w / w.sum())
    pose, share, std = mode_near_best(poses, log_w, 1.0)
    # Brute force: the members by an explicit loop, their weighted mean and std.
    members = [i for i in range(1000) if math.hypot(*(poses[i, :2] - poses[7, :2])) < 1.0]
    wm = w[members] / w.sum()
    assert share == pytest.approx(wm.sum(), rel=1e-9)
    wn = wm / wm.sum()
    mean = wn @ poses[members, :2]
    np.testing.assert_allclose(pose[:2], mean, atol=1e-9)
    theta = math.atan2(wn @ np.sin(poses[members, 2]), wn @ np.cos(poses[members, 2]))
    assert pose[2] == pytest.approx(theta, abs=1e-9)  # around +-pi: the circular mean, not the arithmetic one
    spread = math.sqrt(wn @ ((poses[members, :2] - mean) ** 2).sum(axis=1))
    assert std == pytest.approx(spread, rel=1e-6)
    j, sums = _mode_sums_numpy(poses, log_w, 1.0)  # the numpy twin gives the same sums
    assert j == 7
    assert sums[0] == pytest.approx(share, rel=1e-12)
