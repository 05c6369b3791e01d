"""Whitening: identity covariance on the fit set, capped dimensions, learned whitening shrinks pair gaps, npz."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.retrieval.whitening import LearnedWhitening, PCAWhitening, ShrinkageWhitening, geo_pairs, l2_normalize


def _data(n=400, d=16, seed=0):
    rng = np.random.default_rng(seed)
    return l2_normalize(rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) + 3 * rng.normal(size=d))


def test_pca_whitening_gives_identity_covariance_on_the_fit_set():
    x = _data()
    w = PCAWhitening().fit(x)
    y = w.transform(x, normalize=False)
    np.testing.assert_allclose(np.cov(y, rowvar=False), np.eye(16), atol=2e-4)
    np.testing.assert_allclose(y.mean(axis=0), 0, atol=1e-5)
    assert w.n_components_ == 16 and w.cap_reason_ == "asked"
    np.testing.assert_allclose(np.linalg.norm(w.transform(x), axis=1), 1, rtol=1e-5)


def test_dimension_is_capped_by_what_the_data_supports():
    x = _data(n=10, d=16)
    assert PCAWhitening().fit(x).n_components_ == 9  # 10 samples span 9 directions around their mean
    assert PCAWhitening(n_components=4).fit(x).cap_reason_ == "asked"
    flat = np.hstack([_data(n=50, d=3), np.zeros((50, 5))])  # 3 informative features of 8
    w = PCAWhitening().fit(flat)
    assert w.n_components_ <= 3 and w.cap_reason_ in ("non-degenerate axes", "asked")


def test_learned_whitening_shrinks_differences_within_pairs():
    rng = np.random.default_rng(1)
    places = rng.normal(size=(60, 12))
    nuisance = np.zeros(12)
    nuisance[:3] = 1.0  # views of one place differ mostly along the first three axes
    views = np.vstack([places + rng.normal(size=(60, 12)) * (0.05 + 2 * nuisance) for _ in range(2)])
    x = l2_normalize(views)
    pairs = np.column_stack([np.arange(60), np.arange(60) + 60])
    lw = LearnedWhitening().fit(x, pairs)
    pca = PCAWhitening().fit(x)

    def pair_gap(t):
        y = t.transform(x)
        same = np.linalg.norm(y[pairs[:, 0]] - y[pairs[:, 1]], axis=1).mean()
        other = np.linalg.norm(y[pairs[:, 0]] - y[np.roll(pairs[:, 1], 7)], axis=1).mean()
        return same / other

    assert pair_gap(lw) < 0.7 * pair_gap(pca)


def test_saved_arrays_round_trip_without_pickles(tmp_path):
    x = _data()
    for w in (PCAWhitening(n_components=8).fit(x), LearnedWhitening().fit(x, np.array([[0, 1], [2, 3], [4, 5]]))):
        path = w.save(tmp_path / f"{w.KIND}.npz")
        back = type(w).load(path)
        np.testing.assert_array_equal(back.transform(x), w.transform(x))
        assert back.n_components_ == w.n_components_ and back.cap_reason_ == w.cap_reason_
    with pytest.raises(InputError, match="not a learned_whitening"):
        LearnedWhitening.load(tmp_path / "pca_whitening.npz")
    np.savez(tmp_path / "evil.npz", kind=np.array([object()], dtype=object))
    with pytest.raises(ValueError):  # object arrays would need pickle: refused
        PCAWhitening.load(tmp_path / "evil.npz")


def test_geo_pairs_against_brute_force():
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 10, size=(80, 2))
    th = rng.uniform(-np.pi, np.pi, size=80)
    group = rng.integers(0, 20, size=80)
    got = {tuple(p) for p in geo_pairs(xy, th, group, max_distance=2.0, max_heading_deg=45)}
    want = set()
    for i in range(80):
        for j in range(i + 1, 80):
            dth = abs((th[i] - th[j] + np.pi) % (2 * np.pi) - np.pi)
            if np.hypot(*(xy[i] - xy[j])) <= 2.0 and dth <= np.radians(45) and group[i] != group[j]:
                want.add((i, j))
    assert got == want and want


def test_shrinkage_whitening_is_pca_whitening_without_regularisation_and_the_identity_with_much():
    x = _data()
    full = ShrinkageWhitening(regularization=0.0).fit(x).transform(x, normalize=False)
    pca = PCAWhitening().fit(x).transform(x, normalize=False)
    # the same whitening up to a rotation and a scale: equal Gram matrices once scaled
    gram_a, gram_b = full @ full.T, pca @ pca.T
    np.testing.assert_allclose(gram_a / gram_a.trace(), gram_b / gram_b.trace(), atol=1e-6)
    w = ShrinkageWhitening(regularization=1e6).fit(x)
    centred = l2_normalize(x - x.mean(axis=0))
    np.testing.assert_allclose(np.sum(w.transform(x) * centred, axis=1), 1.0, atol=1e-4)  # only centring left


def test_shrinkage_regularisation_follows_the_ratio_of_dimensions_to_samples():
    assert ShrinkageWhitening().fit(_data(n=401, d=16)).regularization_ == pytest.approx(10 * 16 / 400)
    assert ShrinkageWhitening(per_dimension=2.0).fit(_data(n=9, d=16)).regularization_ == pytest.approx(2 * 16 / 8)
    few = ShrinkageWhitening().fit(_data(n=9, d=16))
    assert few.n_components_ == 16  # every dimension kept, none divided by a variance 9 samples cannot give
    # with few samples the whitened similarities stay close to the centred ones; PCA whitening's do not
    x = _data(n=9, d=16)
    centred = l2_normalize(x - x.mean(axis=0))
    near = np.abs(few.transform(x) @ few.transform(x).T - centred @ centred.T).max()
    far = np.abs(PCAWhitening().fit(x).transform(x) @ PCAWhitening().fit(x).transform(x).T - centred @ centred.T).max()
    assert near < 0.1 < far


def test_shrinkage_whitening_round_trips(tmp_path):
    x = _data()
    w = ShrinkageWhitening().fit(x)
    back = ShrinkageWhitening.load(w.save(tmp_path / "s.npz"))
    np.testing.assert_array_equal(back.transform(x), w.transform(x))
    assert back.regularization is None and back.regularization_ == w.regularization_
