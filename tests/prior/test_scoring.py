"""Correlation re-scoring and the per-class Gaussians, against scipy."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal, pearsonr, rankdata, spearmanr

from pipeline.prior.scoring import ClassGaussians, correlation, similarity_from_r, softmax


def test_pearson_and_spearman_match_scipy():
    rng = np.random.default_rng(0)
    q, rows = rng.standard_normal(40), rng.standard_normal((7, 40))
    rows[3] = np.round(rows[3], 1)  # ties: Spearman averages their ranks
    got_p = correlation(q, rows, method="pearson")
    got_s = correlation(q, rows, method="spearman")
    for i, r in enumerate(rows):
        assert got_p[i] == pytest.approx(pearsonr(q, r).statistic, abs=1e-12)
        assert got_s[i] == pytest.approx(spearmanr(q, r).statistic, abs=1e-12)


def test_spearman_is_pearson_on_ranks():
    rng = np.random.default_rng(1)
    q, rows = rng.standard_normal(30), rng.standard_normal((5, 30)) ** 3
    ranks = rankdata(rows, axis=1)
    np.testing.assert_allclose(correlation(q, rows, method="spearman"),
                               correlation(rankdata(q), ranks, method="pearson"), atol=1e-12)
    # and it ignores any increasing transform, which Pearson does not
    np.testing.assert_allclose(correlation(q, np.exp(rows), method="spearman"),
                               correlation(q, rows, method="spearman"), atol=1e-12)
    assert not np.allclose(correlation(q, np.exp(rows), method="pearson"), correlation(q, rows, method="pearson"))


def test_similarity_is_one_minus_the_normalised_distance():
    np.testing.assert_allclose(similarity_from_r(np.array([-1.0, 0.0, 1.0])), [0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="pearson or spearman"):
        correlation(np.zeros(3), np.zeros((1, 3)), method="kendall")


def _classes(rng, d=6, sizes=(30, 12, 1)):
    x = np.vstack([rng.standard_normal((n, d)) * (0.5 + k) + 3 * k for k, n in enumerate(sizes)])
    labels = np.repeat(np.arange(len(sizes)), sizes)
    return x, labels


def test_gaussian_scores_match_scipy():
    rng = np.random.default_rng(2)
    x, labels = _classes(rng)
    g = ClassGaussians().fit(x, labels)
    y = rng.standard_normal(6) + 2
    got = g.log_likelihood(y)
    for k in range(3):
        ref = multivariate_normal(g.mean_[k], g.covariance(k)).logpdf(y)
        assert got[k] == pytest.approx(ref, rel=1e-6)
        assert g.mahalanobis2(y, k) == pytest.approx(
            (y - g.mean_[k]) @ np.linalg.solve(g.covariance(k), y - g.mean_[k]), rel=1e-6)


def test_covariance_is_the_shrunk_sample_covariance():
    from sklearn.covariance import ledoit_wolf_shrinkage

    rng = np.random.default_rng(3)
    x, labels = _classes(rng)
    g = ClassGaussians().fit(x, labels)
    rows = x[labels == 0]
    alpha = ledoit_wolf_shrinkage(rows - rows.mean(0), assume_centered=True)
    want = (1 - alpha) * np.cov(rows, rowvar=False, bias=True) + alpha * g.sigma2_ * np.eye(6)
    np.testing.assert_allclose(g.covariance(0), want, rtol=1e-6, atol=1e-8)
    # a one-image class is a sphere of the pooled within-class variance
    np.testing.assert_allclose(g.covariance(2), g.sigma2_ * np.eye(6), rtol=1e-6)
    fixed = ClassGaussians(shrinkage=0.25).fit(x, labels)
    assert fixed.alpha_[0] == 0.25 and fixed.alpha_[2] == 1.0


def test_update_refits_only_the_named_classes():
    rng = np.random.default_rng(4)
    x, labels = _classes(rng)
    g = ClassGaussians().fit(x, labels)
    before = {f: np.copy(getattr(g, f)) for f in ("mean_", "chol_", "logdet_")}
    extra = rng.standard_normal((5, 6)) + 10
    x2, labels2 = np.vstack([x, extra]), np.r_[labels, np.full(5, 3)]
    g.update(x2, labels2, [3])
    assert len(g.mean_) == 4 and g.count_[3] == 5
    for f, v in before.items():
        np.testing.assert_array_equal(getattr(g, f)[:3], v)
    np.testing.assert_allclose(g.mean_[3], extra.mean(0))
    with pytest.raises(ValueError, match="no vectors"):
        g.update(x2, labels2, [5])


def test_gaussians_round_trip_as_arrays(tmp_path):
    rng = np.random.default_rng(5)
    x, labels = _classes(rng)
    g = ClassGaussians(shrinkage=0.1).fit(x, labels)
    np.savez(tmp_path / "g.npz", **g.arrays())
    with np.load(tmp_path / "g.npz", allow_pickle=False) as z:
        h = ClassGaussians.from_arrays(z)
    y = rng.standard_normal(6)
    np.testing.assert_array_equal(h.log_likelihood(y), g.log_likelihood(y))
    assert h.shrinkage == 0.1


def test_softmax_is_stable_and_normalised():
    p = softmax(np.array([1000.0, 999.0, -1e9]))
    assert p.sum() == pytest.approx(1.0) and p[0] == pytest.approx(1 / (1 + np.exp(-1)))
