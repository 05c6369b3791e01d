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


def test_top1_distance_is_the_distance_to_the_first_result_and_gross_errors_are_counted():
    from pipeline.retrieval.evaluate import FAR_M, measure
    from pipeline.retrieval.metrics import top1_distances

    q = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 5.0, 1.0]])
    db = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    ranked = np.array([[0, 1, 2], [2, 0, 1], [1, 0, 2]])
    np.testing.assert_allclose(top1_distances(ranked, q, db), [5.0, 10.0, 5.0])
    # Top-1s at 5 m, exactly 10 m (not beyond) and sqrt(20^2 + 5^2) m.
    m = measure(np.array([[0, 1, 2], [2, 0, 1], [2, 0, 1]]), q, db)
    assert m["top1"][f"beyond_{FAR_M:g}m"] == pytest.approx(1 / 3)
    assert m["top1"]["median_m"] == pytest.approx(10.0)
