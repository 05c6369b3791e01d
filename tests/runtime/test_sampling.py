"""KLD-sampling against the chi-square bound, systematic resampling's unbiasedness, wrapping heading bins."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from pipeline.runtime.sampling import kld_count, kld_resample, kld_z, low_variance_indices, pose_bins


def test_z_is_the_normal_quantile_not_the_confidence():
    assert kld_z(0.01) == pytest.approx(2.326348, abs=1e-6)
    assert kld_z(0.05) == pytest.approx(1.644854, abs=1e-6)


@pytest.mark.parametrize("k", [2, 5, 10, 50, 200, 1000])
@pytest.mark.parametrize(("err", "delta"), [(0.05, 0.01), (0.01, 0.01), (0.1, 0.05)])
def test_kld_count_matches_the_chi_square_quantile(k, err, delta):
    """Fox 2003: n = chi2_{k-1, 1-delta} / (2 eps); Wilson-Hilferty is within 1% (2% at k = 2)."""
    exact = chi2.ppf(1 - delta, k - 1) / (2 * err)
    assert kld_count(k, err, delta) == pytest.approx(exact, rel=0.02 if k == 2 else 0.01, abs=1.0)


@pytest.mark.parametrize(("k", "at_least"), [(10, 1.6), (100, 1.15)])
def test_nav2s_z_asks_for_fewer_particles(k, at_least):
    # What nav2 computes by passing pop_z = 0.99 as the z value.
    err = 0.05
    a = 2 / (9 * (k - 1))
    nav2 = (k - 1) / (2 * err) * (1 - a + math.sqrt(a) * 0.99) ** 3
    assert kld_count(k, err, 0.01) / nav2 > at_least
    assert kld_count(1, err, 0.01) == 0 and kld_count(0, err, 0.01) == 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 10.0), min_size=1, max_size=40).filter(lambda w: sum(w) > 1e-6),
       st.integers(1, 500), st.integers(0, 2**31))
def test_systematic_counts_are_floor_or_ceil_of_expected(weights, n, seed):
    w = np.array(weights)
    idx = low_variance_indices(w, n, np.random.default_rng(seed))
    assert len(idx) == n and np.all(np.diff(idx) >= 0)
    counts = np.bincount(idx, minlength=len(w))
    expected = n * w / w.sum()
    assert np.all(counts >= np.floor(expected - 1e-9)) and np.all(counts <= np.ceil(expected + 1e-9))


def test_resampling_is_unbiased_over_draws():
    w = np.array([0.05, 0.5, 0.0, 0.2, 0.25])
    rng = np.random.default_rng(0)
    n = 7
    mean = np.mean([np.bincount(low_variance_indices(w, n, rng), minlength=5) for _ in range(20000)], axis=0)
    np.testing.assert_allclose(mean, n * w, atol=0.02)


def test_bad_weights_are_refused():
    with pytest.raises(ValueError, match="finite"):
        low_variance_indices(np.array([0.0, 0.0]), 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="finite"):
        low_variance_indices(np.array([1.0, np.nan]), 3, np.random.default_rng(0))


def test_heading_bins_wrap():
    a = np.array([[0.2, 0.2, math.pi - 1e-9], [0.2, 0.2, -math.pi], [0.2, 0.2, math.pi + 0.01 - 2 * math.pi]])
    keys = pose_bins(a, 0.5, math.radians(10))
    assert keys[1] == keys[2] != keys[0]  # -pi and -pi + 0.01: the first bin; pi - eps: the last one
    b = a.copy()
    b[:, 2] += 2 * math.pi
    np.testing.assert_array_equal(pose_bins(b, 0.5, math.radians(10)), keys)


def test_kld_keeps_few_particles_for_a_tight_belief_and_many_for_a_spread_one():
    rng = np.random.default_rng(1)
    kw = dict(min_n=100, max_n=5000, err=0.05, delta=0.01, bin_xy=0.5, bin_theta=math.radians(10), rng=rng)
    # Centred in one (x, y, heading) bin: 0.5 m cells and 10-degree heading bins starting at -180.
    tight = np.column_stack([rng.normal(2.25, 0.04, 3000), rng.normal(3.25, 0.04, 3000),
                             rng.normal(math.radians(5), 0.02, 3000)])
    spread = np.column_stack([rng.uniform(0, 40, 3000), rng.uniform(0, 30, 3000), rng.uniform(-3.1, 3.1, 3000)])
    w = np.ones(3000)
    n_tight = len(kld_resample(tight, w, **kw))
    n_spread = len(kld_resample(spread, w, **kw))
    assert n_tight == 100  # a handful of bins: the minimum
    assert n_spread == 5000  # thousands of bins: the maximum
    # In between, the kept count satisfies the bound for the bins its particles occupy, and is the first that does.
    mid = np.column_stack([rng.normal(5, 0.6, 3000), rng.normal(5, 0.6, 3000), rng.normal(0, 0.3, 3000)])
    kept = kld_resample(mid, w, **kw)
    k = len(np.unique(pose_bins(kept, 0.5, math.radians(10))))
    assert 100 < len(kept) < 5000 and len(kept) >= kld_count(k, 0.05, 0.01)
    k_before = len(np.unique(pose_bins(kept[:-1], 0.5, math.radians(10))))
    assert len(kept) - 1 < max(kld_count(k_before, 0.05, 0.01), 100)
