"""Odometry motion model of Thrun, Burgard & Fox, *Probabilistic Robotics*, section 5.4 (numpy only).

A relative motion between two poses of one frame is decomposed into (rot1, trans, rot2): turn by rot1
towards the new position, drive `trans` metres straight, turn by rot2 to the new heading. The particle
filter samples noisy versions of the odometry's decomposition (`sample_motion_model_odometry`), and
`pipeline.io.odometry` uses the same noise to synthesise odometry from ground truth, so the filter's
motion model matches the data it is tested on.

Poses are (..., 3) arrays (x, y, theta), angles in radians. No torch here: the runtime must run
on a robot without it.
"""

from __future__ import annotations

import numpy as np

#: Translation (m) below which the direction of travel is meaningless and rot1 is set to 0; nav2 amcl's value.
NAV2_MIN_TRANS = 0.01


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Angle(s) wrapped into [-pi, pi)."""
    w = (np.asarray(angle, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
    # Rounding can land exactly on +pi (e.g. -pi - 1e-17 -> 2 pi - pi); that belongs at -pi.
    return np.where(w >= np.pi, w - 2.0 * np.pi, w)


def compose2d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) a * b for (N, 3) arrays of x, y, heading (e.g. map_from_odom * odom_from_base)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            wrap_angle(a[:, 2] + b[:, 2])])


def inverse2d(a: np.ndarray) -> np.ndarray:
    """SE(2) inverses of (N, 3) poses."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], wrap_angle(-a[:, 2])])


def odometry_delta(
    prev_pose: np.ndarray, cur_pose: np.ndarray, *, min_trans: float = 1e-9
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rot1, trans, rot2) taking `prev_pose` to `cur_pose` (one frame), broadcast over leading axes.

    rot1 is 0 when trans < `min_trans`, so a turn on the spot is all rot2 rather than a random
    heading towards sensor jitter. The default keeps `compose_odometry` an exact inverse; the
    filter passes `NAV2_MIN_TRANS` as nav2 does.
    """
    prev = np.asarray(prev_pose, dtype=np.float64)
    cur = np.asarray(cur_pose, dtype=np.float64)
    dx = cur[..., 0] - prev[..., 0]
    dy = cur[..., 1] - prev[..., 1]
    trans = np.hypot(dx, dy)
    rot1 = np.where(trans < min_trans, 0.0, wrap_angle(np.arctan2(dy, dx) - prev[..., 2]))
    rot2 = wrap_angle(cur[..., 2] - prev[..., 2] - rot1)
    return rot1, trans, rot2


def compose_odometry(pose: np.ndarray, rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray) -> np.ndarray:
    """Apply (rot1, trans, rot2) to pose(s), the inverse of `odometry_delta`: (..., 3), theta wrapped."""
    pose = np.asarray(pose, dtype=np.float64)
    heading = pose[..., 2] + rot1
    return np.stack(
        [
            pose[..., 0] + trans * np.cos(heading),
            pose[..., 1] + trans * np.sin(heading),
            wrap_angle(heading + rot2),
        ],
        axis=-1,
    )


def _noise_magnitude(rot: np.ndarray) -> np.ndarray:
    """|rot|, but driving backwards (rot near +-pi) counts as a small turn, as in nav2 amcl's diff model.

    Without this a robot reversing 1 cm gets rot1 ~ pi and so rotational noise of ~sqrt(alpha1)*pi.
    """
    rot = np.abs(wrap_angle(rot))
    return np.minimum(rot, np.pi - rot)


def motion_noise_std(
    rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray, alpha: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Standard deviations of the (rot1, trans, rot2) noise (Probabilistic Robotics table 5.6, as nav2).

    std_rot1 = sqrt(a1 rot1^2 + a2 trans^2); std_trans = sqrt(a3 trans^2 + a4 rot1^2 + a4 rot2^2);
    std_rot2 = sqrt(a1 rot2^2 + a2 trans^2), with rotations measured by `_noise_magnitude`.
    """
    a1, a2, a3, a4 = (float(a) for a in np.asarray(alpha, dtype=np.float64).reshape(4))
    r1, r2 = _noise_magnitude(rot1), _noise_magnitude(rot2)
    t2 = np.square(trans)
    return (
        np.sqrt(a1 * r1**2 + a2 * t2),
        np.sqrt(a3 * t2 + a4 * r1**2 + a4 * r2**2),
        np.sqrt(a1 * r2**2 + a2 * t2),
    )


def sample_odometry_deltas(
    rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray, alpha: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy copies (rot1_hat, trans_hat, rot2_hat) of a decomposition; shapes broadcast.

    The three normal draws are taken in one call of shape (3, *shape), so results depend only on the
    generator's state and the shape: reproducible for a seed.
    """
    rot1, trans, rot2 = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (rot1, trans, rot2)))
    s1, st, s2 = motion_noise_std(rot1, trans, rot2, alpha)
    z = rng.standard_normal((3, *rot1.shape))
    return wrap_angle(rot1 - s1 * z[0]), trans - st * z[1], wrap_angle(rot2 - s2 * z[2])


def sample_motion_model_odometry(
    particles: np.ndarray,
    odom_prev: np.ndarray,
    odom_cur: np.ndarray,
    alpha: np.ndarray,
    rng: np.random.Generator,
    *,
    min_trans: float = NAV2_MIN_TRANS,
) -> np.ndarray:
    """Move (N, 3) particles by the odometry reading odom_prev -> odom_cur with independent noise each.

    `alpha` = (alpha1, alpha2, alpha3, alpha4) of table 5.6. The odometry's decomposition is the same
    for every particle; each particle then draws its own noisy decomposition and applies it from its
    own heading. Backward motion is handled as nav2 does: the sampled rot1 stays near pi (the motion is
    still reproduced exactly with zero noise), but the noise is scaled by the turn relative to driving
    straight forwards or backwards (`_noise_magnitude`). As in nav2, a translation under `min_trans`
    (1 cm) is applied along the particle's heading (rot1 = 0): with zero noise the motion is reproduced
    exactly above that, within 2 `min_trans` below it. Returns new (N, 3) particles; input unchanged.
    """
    particles = np.asarray(particles, dtype=np.float64)
    rot1, trans, rot2 = odometry_delta(odom_prev, odom_cur, min_trans=min_trans)
    shape = particles.shape[:-1]
    if np.ndim(rot1) == 0:
        # One odometry reading for all particles: the noise scales are scalars. Same draws (one (3, N)
        # call) and the same arithmetic as `sample_odometry_deltas`, without per-particle copies of them.
        s1, st, s2 = (float(v) for v in motion_noise_std(rot1, trans, rot2, alpha))
        z = rng.standard_normal((3, *shape))
        heading = particles[..., 2] + wrap_angle(float(rot1) - s1 * z[0])
        tr = float(trans) - st * z[1]
        return np.stack([particles[..., 0] + tr * np.cos(heading), particles[..., 1] + tr * np.sin(heading),
                         wrap_angle(heading + wrap_angle(float(rot2) - s2 * z[2]))], axis=-1)
    r1, tr, r2 = sample_odometry_deltas(
        np.broadcast_to(rot1, shape), np.broadcast_to(trans, shape), np.broadcast_to(rot2, shape), alpha, rng
    )
    return compose_odometry(particles, r1, tr, r2)
