"""Two-stage retrieval: exact search against brute force, re-ranking is a permutation, weighted candidates."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.retrieval.search import Database, ExactIndex, region_score, rerank, retrieve
from pipeline.retrieval.whitening import l2_normalize


def _db(n=120, d=24, regions=5, seed=0):
    rng = np.random.default_rng(seed)
    ipa = l2_normalize(rng.normal(size=(n, d)))
    rpa = l2_normalize(rng.normal(size=(n * regions, d)))
    return Database([f"i{k}" for k in range(n)], rng.uniform(0, 20, size=(n, 3)), ipa, rpa,
                    np.arange(0, n * regions + 1, regions))


def test_exact_index_matches_brute_force():
    db = _db()
    q = l2_normalize(np.random.default_rng(5).normal(size=(7, 24)))
    d, i = ExactIndex(db.ipa).search(q, 10)
    brute = np.argsort(((q[:, None, :] - db.ipa[None]) ** 2).sum(-1), axis=1, kind="stable")[:, :10]
    np.testing.assert_array_equal(i, brute)
    np.testing.assert_allclose(d, np.take_along_axis(((q[:, None, :] - db.ipa[None]) ** 2).sum(-1), brute, 1),
                               atol=1e-5)


def test_rerank_is_a_permutation_ordered_by_the_region_rule():
    db = _db()
    first = np.arange(0, 100, 2)
    query_regions = db.regions(42)[:3] + 0.01  # close to image 42's regions
    ranked, scores = rerank(db, first, l2_normalize(query_regions))
    assert sorted(ranked.tolist()) == sorted(first.tolist())
    assert ranked[0] == 42
    for i, s in zip(first, scores, strict=True):  # the rule: mean over query regions of the best match
        want = np.mean(np.max(l2_normalize(query_regions) @ db.regions(int(i)).T, axis=1))
        assert s == pytest.approx(want, abs=1e-6)
    assert np.all(np.diff(scores[np.searchsorted(first, ranked)]) <= 1e-12)


def test_candidates_carry_poses_and_normalised_4321_weights():
    db = _db()
    res = retrieve(db, ExactIndex(db.ipa), db.ipa[17], db.regions(17), top_n=50)
    assert res.ranked[0] == 17 and len(res.first) == 50
    np.testing.assert_allclose(res.candidates[:, 3], [0.4, 0.3, 0.2, 0.1])
    np.testing.assert_allclose(res.candidates[:, :3], db.poses[res.ranked[:4]])
    plain = retrieve(db, ExactIndex(db.ipa), db.ipa[17], None, top_n=50)
    np.testing.assert_array_equal(plain.ranked, plain.first)


def test_region_score_of_nothing_ranks_last():
    assert region_score(np.zeros((0, 4)), np.ones((2, 4))) == -1.0
