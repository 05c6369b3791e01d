"""Retrieval measures against geo-tags: positives, recall@N and mean average precision at Top-K.

A database image is a positive for a query when it lies within `distance` metres and `heading` degrees
of the query's pose. recall@N: the share of queries (with at least one positive) that have a positive
among their first N results. AP@K = sum over i <= K of precision@i x rel(i), divided by min(K, number of
positives); mAP@K averages it over the queries with at least one positive (the paper's "MAP for the
Top-4 re-ranked images" is mAP@4).
"""

from __future__ import annotations

import numpy as np


def positives(query_poses: np.ndarray, db_poses: np.ndarray, distance: float, heading_deg: float) -> np.ndarray:
    """(Q, N) bool: database image j is a positive of query i."""
    d = np.linalg.norm(query_poses[:, None, :2] - db_poses[None, :, :2], axis=2)
    dth = np.abs(np.angle(np.exp(1j * (query_poses[:, None, 2] - db_poses[None, :, 2]))))
    return (d <= distance) & (dth <= np.radians(heading_deg))


def relevance(ranked: np.ndarray, positive: np.ndarray) -> np.ndarray:
    """(Q, L) bool: whether each ranked result is a positive of its query."""
    return np.take_along_axis(positive, np.asarray(ranked), axis=1)


def recall_at(rel: np.ndarray, has_positive: np.ndarray, n: int) -> float:
    return float(np.mean(rel[has_positive, :n].any(axis=1))) if has_positive.any() else float("nan")


def average_precision_at(rel_row: np.ndarray, n_positive: int, k: int) -> float:
    r = np.asarray(rel_row[:k], dtype=np.float64)
    if n_positive == 0:
        return float("nan")
    precision = np.cumsum(r) / np.arange(1, len(r) + 1)
    return float(np.sum(precision * r) / min(k, n_positive))


def map_at(rel: np.ndarray, positive: np.ndarray, k: int) -> float:
    counts = positive.sum(axis=1)
    aps = [average_precision_at(rel[i], int(counts[i]), k) for i in range(len(rel)) if counts[i] > 0]
    return float(np.mean(aps)) if aps else float("nan")


def top1_distances(ranked: np.ndarray, query_poses: np.ndarray, db_poses: np.ndarray) -> np.ndarray:
    """(Q,) metres from each query to its Top-1 database image: how far a wrong answer sends the robot."""
    first = np.asarray(ranked)[:, 0]
    return np.linalg.norm(query_poses[:, :2] - db_poses[first, :2], axis=1)

