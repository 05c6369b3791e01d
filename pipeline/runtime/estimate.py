"""The filter's pose estimate: the weighted mean of the heaviest particle cluster, with its covariance.

Clusters are the connected components of occupied (x, y, heading) histogram cells, 26-connected,
with heading cells wrapping around the circle (nav2 amcl clusters its kd-tree leaves the same way).
A single mean over all particles is meaningless while the belief is multi-modal (two symmetric
corridors average to a wall); the heaviest cluster's mean is the pose a robot should act on.
Heading: circular mean; its variance is taken over deviations wrapped around that mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class PoseEstimate:
    pose: np.ndarray  # (3,) x, y, theta of the best cluster
    covariance: np.ndarray  # (3, 3) over x, y, theta
    cluster_weight: float  # share of the total weight in the best cluster
    clusters: int

    @property
    def std_xy(self) -> float:
        """sqrt of the larger eigenvalue of the position covariance, m."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.covariance[:2, :2]).max(), 0.0)))


def _cells(poses: np.ndarray, bin_xy: float, n_theta: int) -> np.ndarray:
    ix = np.floor(poses[:, 0] / bin_xy).astype(np.int64)
    iy = np.floor(poses[:, 1] / bin_xy).astype(np.int64)
    it = np.floor((poses[:, 2] + math.pi) / (2 * math.pi) * n_theta).astype(np.int64) % n_theta
    return np.column_stack([ix, iy, it])


def cluster_labels(poses: np.ndarray, bin_xy: float, bin_theta: float) -> tuple[np.ndarray, int]:
    """(label per particle, number of clusters)."""
    n_theta = max(1, int(round(2 * math.pi / bin_theta)))
    cells = _cells(poses, bin_xy, n_theta)
    base = cells.min(axis=0)
    span = cells.max(axis=0) - base + 3  # +3: room for the -1 / +1 neighbours of the extreme cells
    span[2] = n_theta

    def key(c):
        return ((c[..., 0] - base[0] + 1) * span[1] + (c[..., 1] - base[1] + 1)) * span[2] + c[..., 2]

    uniq, inverse = np.unique(key(cells), return_inverse=True)
    # Decode the unique keys back to cells, then look up each cell's 26 neighbours among them.
    t = uniq % span[2]
    rest = uniq // span[2]
    ucells = np.column_stack([rest // span[1] + base[0] - 1, rest % span[1] + base[1] - 1, t])
    steps = (-1, 0, 1)
    offsets = np.array([(a, b, c) for a in steps for b in steps for c in steps if (a, b, c) != (0, 0, 0)])
    nb = ucells[:, None, :] + offsets[None]
    nb[..., 2] %= n_theta
    nkeys = key(nb).ravel()
    pos = np.clip(np.searchsorted(uniq, nkeys), 0, len(uniq) - 1)
    found = uniq[pos] == nkeys
    src = np.repeat(np.arange(len(uniq)), len(offsets))[found]
    graph = coo_matrix((np.ones(len(src)), (src, pos[found])), shape=(len(uniq), len(uniq)))
    n, labels = connected_components(graph, directed=False)
    return labels[inverse.ravel()], int(n)


def weighted_pose(poses: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (circular for heading) and covariance of poses."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mx, my = float(w @ poses[:, 0]), float(w @ poses[:, 1])
    mt = math.atan2(float(w @ np.sin(poses[:, 2])), float(w @ np.cos(poses[:, 2])))
    dev = np.column_stack([poses[:, 0] - mx, poses[:, 1] - my, (poses[:, 2] - mt + math.pi) % (2 * math.pi) - math.pi])
    cov = (dev * w[:, None]).T @ dev
    return np.array([mx, my, mt]), cov


def estimate_pose(poses: np.ndarray, weights: np.ndarray, bin_xy: float = 0.5,
                  bin_theta: float = math.radians(10.0)) -> PoseEstimate:
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    labels, n = cluster_labels(poses, bin_xy, bin_theta)
    mass = np.bincount(labels, weights=w, minlength=n)
    best = int(np.argmax(mass))
    members = labels == best
    pose, cov = weighted_pose(poses[members], w[members])
    return PoseEstimate(pose, cov, float(mass[best]), n)
