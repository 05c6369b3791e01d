"""Retrieval measures on hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.retrieval.metrics import average_precision_at, map_at, positives, recall_at, relevance


def test_positives_use_distance_and_wrapped_heading():
    q = np.array([[0.0, 0.0, np.radians(175)]])
    db = np.array([[1.0, 0.0, np.radians(-175)], [1.0, 0.0, 0.0], [3.0, 0.0, np.radians(175)]])
    np.testing.assert_array_equal(positives(q, db, 2.0, 30.0), [[True, False, False]])


def test_average_precision_by_hand():
    # relevant at ranks 1 and 3 of 4, 2 positives in all: (1/1 + 2/3) / 2
    assert average_precision_at(np.array([1, 0, 1, 0]), 2, 4) == pytest.approx((1 + 2 / 3) / 2)
    # 10 positives but only K = 4 counted: (1 + 1) / 4
    assert average_precision_at(np.array([1, 1, 0, 0]), 10, 4) == pytest.approx(0.5)
    assert average_precision_at(np.array([0, 0, 0, 1]), 1, 4) == pytest.approx(0.25)


def test_recall_and_map_over_queries():
    positive = np.array([[True, False, False, False], [False, False, False, True], [False] * 4])
    ranked = np.array([[0, 1, 2, 3], [0, 1, 2, 3], [0, 1, 2, 3]])
    rel = relevance(ranked, positive)
    has = positive.any(axis=1)
    assert recall_at(rel, has, 1) == 0.5 and recall_at(rel, has, 4) == 1.0
    assert map_at(rel, positive, 4) == pytest.approx((1.0 + 0.25) / 2)  # the query without positives is left out
