"""Synthetic wheel odometry for logs whose only trajectory is the corrected (ground-truth) one.

The corrected CARMEN logs carry no raw odometry (their ODOM lines follow the corrected path), so the
odometry a localizer sees is made here: every ground-truth step is decomposed into (rot1, trans, rot2)
in the robot's frame, perturbed with the odometry motion model's noise (Probabilistic Robotics
table 5.6, the model the particle filter assumes) and integrated from (0, 0, 0) in the odom frame.
The odometry therefore drifts like a real robot's and is reproducible for a seed.
"""

from __future__ import annotations

import json

import numpy as np

from pipeline.config import OdometryNoise
from pipeline.runtime.motion import odometry_delta, sample_odometry_deltas, wrap_angle


def noise_alphas(noise: OdometryNoise) -> np.ndarray:
    """(alpha1, alpha2, alpha3, alpha4) as the array the motion model takes."""
    return np.array([noise.alpha1, noise.alpha2, noise.alpha3, noise.alpha4], dtype=np.float64)


def noise_json(noise: OdometryNoise) -> str:
    """The alphas as compact, key-sorted JSON (for table metadata; stable across runs)."""
    return json.dumps(noise.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def integrate_deltas(rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray) -> np.ndarray:
    """Odom-frame poses (N+1, 3) from (0, 0, 0) after applying N decompositions in order.

    Vectorised: heading before step k is the sum of all earlier rotations, positions are cumulative sums.
    """
    turns = np.concatenate([[0.0], np.cumsum(rot1 + rot2)])  # unwrapped heading after each step
    heading = turns[:-1] + rot1  # direction of travel of step k
    x = np.concatenate([[0.0], np.cumsum(trans * np.cos(heading))])
    y = np.concatenate([[0.0], np.cumsum(trans * np.sin(heading))])
    return np.stack([x, y, wrap_angle(turns)], axis=1)


def synthesise_odometry(gt_poses: np.ndarray, noise: OdometryNoise, seed: int) -> np.ndarray:
    """Noisy odom_from_base poses (N, 3) for ground-truth map_from_base poses (N, 3); the first is (0, 0, 0).

    With all alphas 0 the result is the ground truth expressed relative to its first pose.
    """
    gt = np.asarray(gt_poses, dtype=np.float64)
    if gt.ndim != 2 or gt.shape[1] != 3:
        raise ValueError(f"gt_poses must be (N, 3), got {gt.shape}")
    if len(gt) == 0:
        return np.zeros((0, 3))
    rot1, trans, rot2 = odometry_delta(gt[:-1], gt[1:])
    rng = np.random.default_rng(seed)
    return integrate_deltas(*sample_odometry_deltas(rot1, trans, rot2, noise_alphas(noise), rng))


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """Poses (N, 3) in the frame of the first one: first_from_base = inv(map_from_first) * map_from_base."""
    poses = np.asarray(poses, dtype=np.float64)
    x0, y0, t0 = poses[0]
    dx, dy = poses[:, 0] - x0, poses[:, 1] - y0
    c, s = np.cos(t0), np.sin(t0)
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(poses[:, 2] - t0)], axis=1)
