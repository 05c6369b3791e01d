"""evaluate-retrieval's figures per query source, checked by hand on a few poses."""

import numpy as np
import pytest

from pipeline.retrieval.evaluate import by_source, query_sources, report_table


def test_query_sources_name_test_stops_and_run_frames():
    got = query_sources(np.array(["test", "run:query_00", "run:q"], dtype=object))
    assert got.tolist() == ["test stops", "run frames", "run frames"]


def test_figures_by_source_by_hand():
    db = np.array([[0, 0, 0], [1, 0, 0], [10, 0, 0], [0, 0, np.pi]], float)
    queries = np.array([[0.5, 0, 0], [10.5, 0, 0], [50, 0, 0]], float)
    ranked = np.array([[0, 2, 1, 3], [3, 2, 0, 1], [0, 1, 2, 3]])
    out = by_source(ranked, np.array(["test stops", "run frames", "run frames"]), queries, db)
    # The test stop: database 0 and 1 are positives (0.5 m, same heading), found at ranks 1 and 3.
    assert out["test stops"] == {"queries": 1, "queries_with_positive": 1, "nearest_database_m_median": 0.5,
                                 "positives_mean": 2.0, "map_at_4": pytest.approx((1 + 2 / 3) / 2),
                                 "recall_at_1": 1.0, "recall_at_4": 1.0}
    # Run frames: one with its single positive at rank 2, one 40 m from anything (no positive, not averaged).
    assert out["run frames"] == {"queries": 2, "queries_with_positive": 1, "nearest_database_m_median": 20.25,
                                 "positives_mean": 1.0, "map_at_4": 0.5, "recall_at_1": 0.0, "recall_at_4": 1.0}
    text = report_table({"database_images": 4, "query_images": 3, "variants": {},
                         "by_source": {"variant": "ipa+rpa / pca", "sources": out}})
    assert "| test stops | 1 | 1 | 0.50 m | 2.00 | 0.833 | 1.000 | 1.000 |" in text
    assert "| run frames | 2 | 1 | 20.25 m | 1.00 | 0.500 | 0.000 | 1.000 |" in text
