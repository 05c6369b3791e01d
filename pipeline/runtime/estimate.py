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

from pipeline.runtime.sampling import heading_bins, pose_cells


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


def cluster_labels(poses: np.ndarray, bin_xy: float, bin_theta: float) -> tuple[np.ndarray, int]:
    """(label per particle, number of clusters)."""
    from pipeline.runtime.kernels import HAVE_NUMBA

    n_theta = heading_bins(bin_theta)
    cells = pose_cells(poses, bin_xy, n_theta)
    base = cells.min(axis=0)
    span = cells.max(axis=0) - base + 3  # +3: room for the -1 / +1 neighbours of the extreme cells
    span[2] = n_theta
    keys = ((cells[:, 0] - base[0] + 1) * span[1] + (cells[:, 1] - base[1] + 1)) * span[2] + cells[:, 2]
    uniq, inverse = np.unique(keys, return_inverse=True)
    if HAVE_NUMBA:
        ulabels, n = _label_sorted_keys(uniq, int(span[1]), int(span[2]))
    else:  # pragma: no cover - the scipy twin, kept for machines without numba
        ulabels, n = _label_sorted_keys_scipy(uniq, int(span[1]), int(span[2]))
    return ulabels[inverse.ravel()], int(n)


def _neighbour_keys(key: int, span1: int, n_theta: int):
    """The 26 neighbours' keys of a cell key (heading wraps), as a generator of ints."""
    t = key % n_theta
    rest = key // n_theta
    x, y = rest // span1, rest % span1
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            for c in (-1, 0, 1):
                if a == 0 and b == 0 and c == 0:
                    continue
                yield ((x + a) * span1 + (y + b)) * n_theta + (t + c) % n_theta


def _label_sorted_keys_scipy(uniq: np.ndarray, span1: int, n_theta: int) -> tuple[np.ndarray, int]:
    src, dst = [], []
    for k, key in enumerate(uniq):
        for nk in _neighbour_keys(int(key), span1, n_theta):
            pos = int(np.searchsorted(uniq, nk))
            if pos < len(uniq) and uniq[pos] == nk:
                src.append(k)
                dst.append(pos)
    graph = coo_matrix((np.ones(len(src)), (src, dst)), shape=(len(uniq), len(uniq)))
    n, labels = connected_components(graph, directed=False)
    return labels, n


try:
    from numba import njit

    @njit(cache=True, nogil=True)
    def _label_sorted_keys(uniq, span1, n_theta):  # pragma: no cover - compiled; twin: the scipy path
        k_total = uniq.shape[0]
        parent = np.arange(k_total)

        def find(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for k in range(k_total):
            key = uniq[k]
            t = key % n_theta
            rest = key // n_theta
            x = rest // span1
            y = rest % span1
            for a in range(-1, 2):
                for b in range(-1, 2):
                    for c in range(-1, 2):
                        if a == 0 and b == 0 and c == 0:
                            continue
                        nk = ((x + a) * span1 + (y + b)) * n_theta + (t + c) % n_theta
                        pos = np.searchsorted(uniq, nk)
                        if pos < k_total and uniq[pos] == nk:
                            ra, rb = find(k), find(pos)
                            if ra != rb:
                                parent[max(ra, rb)] = min(ra, rb)
        labels = np.empty(k_total, dtype=np.int64)
        n = 0
        remap = np.full(k_total, -1, dtype=np.int64)
        for k in range(k_total):
            r = find(k)
            if remap[r] < 0:
                remap[r] = n
                n += 1
            labels[k] = remap[r]
        return labels, n
except ImportError:  # pragma: no cover
    _label_sorted_keys = None


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


def _mode_sums_numpy(poses: np.ndarray, log_w: np.ndarray, radius: float) -> tuple[int, np.ndarray]:
    """(index of the heaviest particle, [weight, sum w dx, sum w dy, sum w |d|^2, sum w sin, sum w cos] over the
    particles within `radius` of it): the numpy twin of `_mode_sums`."""
    j = int(np.argmax(log_w))
    d = poses[:, :2] - poses[j, :2]
    d2 = np.einsum("ij,ij->i", d, d)
    near = d2 < radius * radius
    w = np.exp(log_w[near])
    th = poses[near, 2]
    return j, np.array([w.sum(), w @ d[near, 0], w @ d[near, 1], w @ d2[near], w @ np.sin(th), w @ np.cos(th)])


try:
    from numba import njit as _njit

    @_njit(cache=True, nogil=True)
    def _mode_sums(poses, log_w, radius):  # pragma: no cover - compiled; twin: _mode_sums_numpy
        j = 0
        for i in range(1, log_w.shape[0]):
            if log_w[i] > log_w[j]:
                j = i
        x0, y0, r2 = poses[j, 0], poses[j, 1], radius * radius
        out = np.zeros(6)
        for i in range(poses.shape[0]):
            dx, dy = poses[i, 0] - x0, poses[i, 1] - y0
            d2 = dx * dx + dy * dy
            if d2 < r2:
                w = math.exp(log_w[i])
                out[0] += w
                out[1] += w * dx
                out[2] += w * dy
                out[3] += w * d2
                out[4] += w * math.sin(poses[i, 2])
                out[5] += w * math.cos(poses[i, 2])
        return j, out
except ImportError:  # pragma: no cover
    _mode_sums = _mode_sums_numpy


def mode_near_best(poses: np.ndarray, log_w: np.ndarray, radius: float = 1.0) -> tuple[np.ndarray, float, float]:
    """The belief's mode: the weighted mean of the particles within `radius` (m) of the heaviest one.

    `log_w` must be normalised (the weights are exp(log_w), summing to 1). Returns (pose (3,), the weight
    those particles hold, their position std in m). One pass over the particles (the filter asks after
    every measurement).
    """
    j, s = _mode_sums(np.ascontiguousarray(poses, dtype=np.float64), np.ascontiguousarray(log_w, dtype=np.float64),
                      float(radius))
    share = float(s[0])
    mx, my = s[1] / share, s[2] / share
    std = math.sqrt(max(s[3] / share - mx * mx - my * my, 0.0))
    pose = np.array([poses[j, 0] + mx, poses[j, 1] + my, math.atan2(s[4], s[5])])
    return pose, share, std
