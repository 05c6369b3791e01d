"""Descriptor compression: shapes and caps, agreement with scikit-learn, npz round trips, properties, memory."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.descriptors.compression import (
    METHODS,
    Compressor,
    GaussianRandomProjectionCompressor,
    IdentityCompressor,
    IncrementalPCACompressor,
    KernelPCACompressor,
    SparseRandomProjectionCompressor,
    load_compressor,
    make_compressor,
)
from pipeline.errors import InputError

N_FIT, N_NEW, D = 60, 25, 300


def _unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture(scope="module")
def data():
    """(fit, new) l2-normalised rows around an 8-d latent structure, as CNN features have a few dominant axes."""
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(8, D))
    x = rng.normal(size=(N_FIT + N_NEW, 8)) @ basis + 0.5 * rng.normal(size=(N_FIT + N_NEW, D))
    x = _unit(x + 2.0 * rng.normal(size=D))
    return x[:N_FIT], x[N_FIT:]


def _close(got, want, rtol=1e-4):
    # Relative to the output's scale: entries near zero make an element-wise rtol meaningless.
    np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * np.abs(want).max())


def _align_signs(got, want):
    """Eigenvectors are defined up to sign: flip each of `got`'s columns to agree with `want`'s."""
    s = np.sign(np.sum(got * want, axis=0))
    s[s == 0] = 1
    return got * s


@pytest.mark.parametrize("method", METHODS)
def test_shapes_dtype_and_caps(method, data):
    x, y = data
    c = make_compressor(method, 16, seed=3)
    z = c.fit_transform(x)
    expect = D if method == "none" else 16
    assert z.shape == (N_FIT, expect) and z.dtype == np.float32 and c.n_components_ == expect
    assert c.n_features_in_ == D and c.transform(y).shape == (N_NEW, expect)
    assert c.cap_reason_ == ("uncompressed" if method == "none" else "asked")
    assert c.transform(y.astype(np.float64)).dtype == np.float32

    big = make_compressor(method, 128).fit(x)  # more components than the 60 fit rows
    want = {"ipca": (N_FIT - 1, {"samples"}), "kpca": (N_FIT - 1, {"non-positive eigenvalues"}),
            "srp": (128, {"asked"}), "grp": (128, {"asked"}), "none": (D, {"uncompressed"})}[method]
    assert big.n_components_ == want[0] and big.cap_reason_ in want[1]
    assert big.transform(y).shape == (N_NEW, want[0])

    narrow = make_compressor(method, 128).fit(x[:, :40] / np.linalg.norm(x[:, :40], axis=1, keepdims=True))
    if method in ("ipca", "srp", "grp"):  # more components than the 40 features
        assert narrow.n_components_ == 40 and narrow.cap_reason_ == "features"


def test_ipca_matches_sklearn(data):
    from sklearn.decomposition import IncrementalPCA

    x, y = data
    c = IncrementalPCACompressor(12).fit(x)
    ref = IncrementalPCA(n_components=12, batch_size=c.batch_size_).fit(x)
    _close(c.transform(y), ref.transform(y))
    # Several batches: the incremental path, not one SVD.
    c2 = IncrementalPCACompressor(4).fit(x)
    assert c2.batch_size_ == 20
    _close(c2.transform(y), IncrementalPCA(n_components=4, batch_size=20).fit(x).transform(y))


def test_kpca_matches_sklearn_on_new_data_and_on_the_fit_set(data):
    from sklearn.decomposition import KernelPCA

    x, y = data
    c = KernelPCACompressor(20, seed=1).fit(x)
    ref = KernelPCA(n_components=20, kernel="rbf", gamma=c.gamma_, random_state=1).fit(x.astype(np.float64))
    _close(_align_signs(c.transform(y), ref.transform(y)), ref.transform(y))
    fit_ref = KernelPCA(n_components=20, kernel="rbf", gamma=c.gamma_, random_state=1).fit_transform(x)
    _close(_align_signs(c.transform(x), fit_ref), fit_ref)
    np.testing.assert_array_equal(c.fit_transform(x), c.transform(x))


def test_kpca_automatic_gamma_is_the_inverse_mean_squared_distance(data):
    x, _ = data
    d2 = ((x[:, None, :].astype(np.float64) - x[None, :, :]) ** 2).sum(-1)
    mean_sq = d2[~np.eye(N_FIT, dtype=bool)].mean()
    assert KernelPCACompressor().fit(x).gamma_ == pytest.approx(1 / mean_sq, rel=1e-6)
    assert KernelPCACompressor(gamma=0.3).fit(x).gamma_ == 0.3


@pytest.mark.parametrize("cls, sk", [(SparseRandomProjectionCompressor, "SparseRandomProjection"),
                                     (GaussianRandomProjectionCompressor, "GaussianRandomProjection")])
def test_random_projections_match_sklearn(cls, sk, data):
    import sklearn.random_projection as rp

    x, y = data
    c = cls(128, seed=7).fit(x)
    ref = getattr(rp, sk)(n_components=128, random_state=7).fit(x)
    want = ref.transform(y)
    _close(c.transform(y), want.toarray() if hasattr(want, "toarray") else want)
    other = cls(128, seed=8).fit(x)
    assert not np.allclose(other.transform(y), c.transform(y))  # the seed is what draws the matrix


@pytest.mark.parametrize("method", ["srp", "grp"])
def test_random_projections_roughly_preserve_distances(method, data):
    x, y = data
    z = np.vstack([x, y])
    p = make_compressor(method, 128, seed=0).fit(x).transform(z)
    iu = np.triu_indices(len(z), 1)
    ratio = np.linalg.norm(p[:, None] - p[None], axis=-1)[iu] / np.linalg.norm(z[:, None] - z[None], axis=-1)[iu]
    assert 0.8 < ratio.mean() < 1.2  # Johnson-Lindenstrauss, with sklearn's 1/sqrt(n_components) scaling
    assert 0.5 < ratio.min() and ratio.max() < 1.5


def test_ipca_components_are_orthonormal(data):
    c = IncrementalPCACompressor(128).fit(data[0])
    np.testing.assert_allclose(c.components_ @ c.components_.T, np.eye(c.n_components_), atol=1e-5)


def test_identity_is_a_float32_copy(data):
    x = data[0]
    c = IdentityCompressor().fit(x)
    z = c.transform(x)
    assert z.dtype == np.float32 and np.array_equal(z, x) and not np.shares_memory(z, x) and c.nbytes() == 0
    assert np.array_equal(c.transform(x.astype(np.float64)), x)


@pytest.mark.parametrize("method", METHODS)
def test_npz_round_trip_without_pickles(method, data, tmp_path):
    x, y = data
    c = make_compressor(method, 24, seed=5).fit(x)
    # Nothing of sklearn is kept: only arrays and plain scalars, so the npz holds all there is.
    assert all(isinstance(v, np.ndarray | int | float | str | type(None)) for k, v in vars(c).items()
               if not k.startswith("_"))
    path = c.save(tmp_path / f"{method}.npz")
    back = load_compressor(path)
    assert type(back) is type(c) and back.get_params() == c.get_params()
    assert (back.n_components_, back.n_features_in_, back.cap_reason_) == (c.n_components_, D, c.cap_reason_)
    np.testing.assert_array_equal(back.transform(y), c.transform(y))
    with np.load(path, allow_pickle=False) as z:
        assert str(z["kind"]) == method and all(z[k].dtype != object for k in z.files)
        assert back.nbytes() == sum(z[a].nbytes for a in type(c).ARRAYS) == c.nbytes()


def test_kpca_gamma_none_survives_the_round_trip(data, tmp_path):
    x, y = data
    auto = load_compressor(KernelPCACompressor(8).fit(x).save(tmp_path / "a.npz"))
    fixed = load_compressor(KernelPCACompressor(8, gamma=0.25).fit(x).save(tmp_path / "b.npz"))
    assert auto.gamma is None and auto.gamma_ > 0 and fixed.gamma == 0.25 == fixed.gamma_


def test_loading_what_is_not_a_compressor_names_the_file(data, tmp_path):
    x, _ = data
    other = tmp_path / "whitening.npz"
    np.savez(other, kind=np.array("pca_whitening"), mean_=np.zeros(3))
    with pytest.raises(InputError, match="whitening.npz.*not a compressor") as e:
        load_compressor(other)
    assert "pca_whitening" in str(e.value) and "ipca" in str(e.value)  # what it holds, and the fix
    bare = tmp_path / "bare.npz"
    np.savez(bare, a=np.zeros(2))
    with pytest.raises(InputError, match="bare.npz"):
        load_compressor(bare)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(InputError, match="junk.npz"):
        load_compressor(junk)
    with pytest.raises(InputError, match="missing.npz"):
        load_compressor(tmp_path / "missing.npz")
    cut = tmp_path / "cut.npz"
    full = dict(np.load(IncrementalPCACompressor(4).fit(x).save(tmp_path / "ok.npz")))
    np.savez(cut, **{k: v for k, v in full.items() if k != "components_"})
    with pytest.raises(InputError, match="cut.npz.*damaged"):
        load_compressor(cut)
    full["components_"] = full["components_"][:, :10]
    np.savez(cut, **full)
    with pytest.raises(InputError, match="shape"):
        load_compressor(cut)


@pytest.mark.parametrize("method", METHODS)
def test_transform_refuses_wrong_feature_count(method, data):
    x, y = data
    c = make_compressor(method, 8).fit(x)
    with pytest.raises(ValueError, match="300"):
        c.transform(y[:, :299])
    with pytest.raises(ValueError):
        c.transform(y[0])  # one row must still be (1, D)
    with pytest.raises(ValueError, match="not fitted"):
        make_compressor(method, 8).transform(y)


def test_memory_ranks_as_in_table_one(data):
    x, _ = data
    size = {m: make_compressor(m, 128).fit(x).nbytes() for m in METHODS}
    assert size["kpca"] > size["ipca"] > size["srp"] and size["none"] == 0
    kpca = KernelPCACompressor(128).fit(x)
    assert kpca.nbytes() >= kpca.X_fit_.nbytes == N_FIT * D * 4  # the stored fit set is what makes it large


def test_make_compressor_refuses_unknown_methods():
    with pytest.raises(ValueError) as e:
        make_compressor("pca")
    assert all(m in str(e.value) for m in METHODS)
    for m in METHODS:
        c = make_compressor(m, 32, seed=4)
        assert isinstance(c, Compressor) and c.KIND == m and (c.n_components, c.seed) == (32, 4)
    with pytest.raises(ValueError, match="positive integer"):
        make_compressor("grp", 0).fit(np.eye(4, dtype=np.float32))
