"""Compression of CNN layer descriptors to a few dimensions (seed 001, Table I: memory, query time, accuracy).

The paper reduces each of three layers (AlexNet pool5 9216-d, fc6 / fc7 4096-d) to 128 dimensions with four
scikit-learn transforms, compared here against the uncompressed descriptor:

- "ipca": Incremental PCA (fitted in batches, so a large database never has to be decomposed at once).
- "kpca": Kernel PCA with an rbf kernel. A query is compared with every fit descriptor, which is why the
  paper finds its memory and query time far above the others: `nbytes` counts the stored fit set.
- "srp" / "grp": sparse / Gaussian random projections (data independent apart from the feature count).
- "none": identity, the uncompressed baseline.

scikit-learn only fits. What is kept are plain arrays, and `transform` is numpy / scipy, so a saved
compressor loads (npz, allow_pickle=False, never a pickle) and runs where scikit-learn is not installed.
Conventions as in `pipeline.retrieval.whitening`: hyperparameters in `__init__`, `fit` returns self, fitted
state ends in `_`, and the output dimension is capped by what the data supports, `cap_reason_` naming the
limit that applied.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.io.atomic import atomic_file

METHODS = ("ipca", "kpca", "srp", "grp", "none")


class Compressor:
    """Base: validation, capping, npz round trip and memory accounting shared by every method."""

    KIND = ""
    PARAMS: tuple[str, ...] = ("n_components", "seed")
    # Arrays a query's transform reads: saved, and summed by `nbytes` (Table I's "transformation" memory).
    ARRAYS: tuple[str, ...] = ()
    SCALARS: tuple[str, ...] = ("n_components_", "n_features_in_", "cap_reason_")
    MIN_SAMPLES = 1

    def __init__(self, n_components: int = 128, *, seed: int = 0):
        self.n_components, self.seed = n_components, seed

    def get_params(self) -> dict:
        return {p: getattr(self, p) for p in self.PARAMS}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.get_params().items())})"

    # -- fitting ---------------------------------------------------------------------------------------

    def fit(self, x: np.ndarray) -> Compressor:
        k = self.n_components
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise ValueError(f"{self.KIND}: n_components must be a positive integer, got {k!r}")
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] < 1:
            raise ValueError(f"{self.KIND}: fit expects a 2-D (samples, features) array, got shape {x.shape}")
        if len(x) < self.MIN_SAMPLES:
            raise ValueError(f"{self.KIND}: fit needs at least {self.MIN_SAMPLES} descriptors, got {len(x)}")
        if not np.isfinite(x).all():
            raise ValueError(f"{self.KIND}: fit descriptors contain NaN or inf")
        self.n_features_in_ = int(x.shape[1])
        self._fit(x)
        return self

    def _fit(self, x: np.ndarray) -> None:
        raise NotImplementedError

    def _cap(self, limits: dict[str, int]) -> None:
        # On a tie "asked" wins: the user got what they asked for, nothing was cut.
        self.cap_reason_ = min(limits, key=lambda k: (limits[k], k != "asked"))
        self.n_components_ = int(limits[self.cap_reason_])

    # -- transforming ----------------------------------------------------------------------------------

    def transform(self, x: np.ndarray) -> np.ndarray:
        if not hasattr(self, "n_features_in_"):
            raise ValueError(f"{self!r} is not fitted: call fit() or load_compressor()")
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.n_features_in_:
            raise ValueError(f"{self.KIND}: expects (N, {self.n_features_in_}) descriptors, got shape {x.shape}")
        return np.ascontiguousarray(self._transform(x), dtype=np.float32)

    def _transform(self, x: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def fit_transform(self, x: np.ndarray) -> np.ndarray:
        # Through `transform`, so the fit set gets exactly the numbers a query would (no sklearn shortcut).
        return self.fit(x).transform(x)

    def nbytes(self) -> int:
        if not hasattr(self, "n_features_in_"):
            raise ValueError(f"{self!r} is not fitted")
        return int(sum(np.asarray(getattr(self, a)).nbytes for a in self.ARRAYS))

    def _expected_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of each array in ARRAYS given the fitted scalars; a loaded file is checked against it."""
        return {}

    # -- npz -------------------------------------------------------------------------------------------

    def save(self, path) -> Path:
        if not hasattr(self, "n_features_in_"):
            raise ValueError(f"{self!r} is not fitted: nothing to save")
        out = {"kind": np.array(self.KIND)}
        for p in self.PARAMS:
            v = getattr(self, p)
            # None (e.g. kpca's automatic gamma) as an empty array: no sentinel value can collide with it.
            out[f"param_{p}"] = np.zeros(0) if v is None else np.array(v)
        for f in self.SCALARS + self.ARRAYS:
            out[f] = np.asarray(getattr(self, f))
        path = Path(path)
        with atomic_file(path, "wb") as fh:
            np.savez(fh, **out)
        return path

    @classmethod
    def _from_npz(cls, z, path: Path) -> Compressor:
        def scalar(key):
            a = z[key]
            if a.ndim != 0:
                raise ValueError(f"'{key}' is not a scalar")
            return a.item()

        params = {p: (None if z[f"param_{p}"].size == 0 else scalar(f"param_{p}")) for p in cls.PARAMS}
        seed = params.pop("seed")
        obj = cls(params.pop("n_components"), seed=seed, **params)
        for f in cls.SCALARS:
            setattr(obj, f, scalar(f))
        for f in cls.ARRAYS:
            setattr(obj, f, z[f])
        for f, shape in obj._expected_shapes().items():
            if getattr(obj, f).shape != shape:
                raise ValueError(f"'{f}' has shape {getattr(obj, f).shape}, expected {shape}")
        return obj


class IncrementalPCACompressor(Compressor):
    KIND = "ipca"
    ARRAYS = ("mean_", "components_")
    SCALARS = Compressor.SCALARS + ("batch_size_",)
    MIN_SAMPLES = 2
    # sklearn's own default batch is 5 x n_features (46k rows for pool5); 5 x n_components keeps each
    # batch's SVD small while every batch still has several times more rows than components.
    BATCH_FACTOR = 5

    def _fit(self, x):
        from sklearn.decomposition import IncrementalPCA

        n, d = x.shape
        # n centred samples span at most n - 1 directions; an n-th axis would be round-off noise that
        # only adds noise to query distances (IPCA itself also needs n_components <= samples per batch).
        self._cap({"asked": int(self.n_components), "samples": n - 1, "features": d})
        self.batch_size_ = int(min(n, self.BATCH_FACTOR * self.n_components_))
        # float32 in: IPCA exists to keep memory bounded, and a float64 copy of the database would double it.
        ipca = IncrementalPCA(n_components=self.n_components_, batch_size=self.batch_size_).fit(x)
        self.mean_ = ipca.mean_.astype(np.float32)
        self.components_ = ipca.components_.astype(np.float32)

    def _transform(self, x):
        return (x - self.mean_) @ self.components_.T

    def _expected_shapes(self):
        return {"mean_": (self.n_features_in_,), "components_": (self.n_components_, self.n_features_in_)}


class KernelPCACompressor(Compressor):
    KIND = "kpca"
    PARAMS = Compressor.PARAMS + ("gamma",)
    ARRAYS = ("X_fit_", "alphas_", "K_fit_rows_", "K_fit_all_")
    SCALARS = Compressor.SCALARS + ("gamma_",)
    MIN_SAMPLES = 2
    CHUNK_BYTES = 64 << 20  # bound on one block of the (queries x fit set) kernel during transform

    def __init__(self, n_components: int = 128, *, seed: int = 0, gamma: float | None = None):
        super().__init__(n_components, seed=seed)
        self.gamma = gamma

    def _fit(self, x):
        from sklearn.decomposition import KernelPCA
        from sklearn.metrics.pairwise import rbf_kernel

        x64 = x.astype(np.float64)
        n = len(x)
        if self.gamma is None:
            # sklearn's default 1 / n_features (1e-4 for pool5) against l2-normalised descriptors, whose
            # squared distances are at most 4, leaves exp(-gamma d^2) ~ 1 - gamma d^2: a linear kernel,
            # i.e. plain PCA. Scaling by the mean squared distance puts typical pairs at exp(-1).
            xc = x64 - x64.mean(axis=0)
            mean_sq = 2.0 * float(np.einsum("ij,ij->", xc, xc)) / (n - 1)  # over pairs i != j, in O(n d)
            if mean_sq <= 0:
                raise ValueError("kpca: all fit descriptors are identical; no gamma can be derived")
            self.gamma_ = 1.0 / mean_sq
        else:
            self.gamma_ = float(self.gamma)
        self._cap({"asked": int(self.n_components), "samples": n})
        k = rbf_kernel(x64, gamma=self.gamma_)
        # KernelCenterer's statistics, taken before sklearn centres the matrix in place.
        self.K_fit_rows_ = k.mean(axis=0)
        self.K_fit_all_ = np.array(self.K_fit_rows_.mean())
        kp = KernelPCA(n_components=self.n_components_, kernel="precomputed", eigen_solver="auto",
                       random_state=self.seed).fit(k)
        # The centred kernel has rank <= n - 1 (and sklearn zeroes eigenvalues below round-off): such axes
        # carry no variance and 1 / sqrt(eigenvalue) would blow query noise up.
        keep = kp.eigenvalues_ > 0
        if not keep.any():
            raise ValueError("kpca: the centred kernel has no positive eigenvalue (degenerate fit set)")
        if not keep.all():
            self.n_components_, self.cap_reason_ = int(keep.sum()), "non-positive eigenvalues"
        self.alphas_ = (kp.eigenvectors_[:, keep] / np.sqrt(kp.eigenvalues_[keep])).astype(np.float32)
        self.X_fit_ = x.copy()

    def _fit_sq_norms(self) -> np.ndarray:
        # Cached, not stored: it is derived from X_fit_ and would otherwise cost one pass over the fit set per query.
        cache = getattr(self, "_sq_cache", None)
        if cache is None or cache[0] is not self.X_fit_:
            cache = (self.X_fit_, np.einsum("ij,ij->i", self.X_fit_, self.X_fit_, dtype=np.float64))
            self._sq_cache = cache
        return cache[1]

    def _transform(self, x):
        n_fit = len(self.X_fit_)
        sq_fit = self._fit_sq_norms()
        out = np.empty((len(x), self.n_components_), dtype=np.float32)
        step = max(1, self.CHUNK_BYTES // (8 * n_fit))
        for s in range(0, len(x), step):
            q = x[s : s + step]
            # The dot product in float32 (BLAS speed, no float64 copy of the fit set); the rest in float64,
            # so the kernel is accurate to ~1e-7 for unit-norm descriptors.
            d2 = np.einsum("ij,ij->i", q, q, dtype=np.float64)[:, None] + sq_fit - 2.0 * (q @ self.X_fit_.T)
            kern = np.exp(-self.gamma_ * np.maximum(d2, 0.0))
            # KernelCenterer.transform, in its order: row means of the raw kernel first. Only K_fit_rows_
            # changes the result exactly (alphas_' columns sum to zero, so per-row constants cancel); the other
            # two terms are kept so the matrix multiplied is sklearn's, small, and free of that cancellation.
            pred_cols = kern.sum(axis=1, keepdims=True) / n_fit
            kern -= self.K_fit_rows_
            kern -= pred_cols
            kern += self.K_fit_all_
            out[s : s + step] = kern @ self.alphas_
        return out

    def _expected_shapes(self):
        n = len(self.X_fit_)
        return {"X_fit_": (n, self.n_features_in_), "alphas_": (n, self.n_components_), "K_fit_rows_": (n,),
                "K_fit_all_": ()}


class SparseRandomProjectionCompressor(Compressor):
    KIND = "srp"
    ARRAYS = ("components_data_", "components_indices_", "components_indptr_", "components_shape_")
    SCALARS = Compressor.SCALARS + ("density_",)

    def _fit(self, x):
        import scipy.sparse as sp
        from sklearn.random_projection import SparseRandomProjection

        # More output than input dimensions would only spread the same information thinner.
        self._cap({"asked": int(self.n_components), "features": x.shape[1]})
        rp = SparseRandomProjection(n_components=self.n_components_, density="auto", random_state=self.seed,
                                    dense_output=True).fit(x)
        c = sp.csr_matrix(rp.components_)  # dense when density reaches 1 (very few features)
        self.density_ = float(rp.density_)
        self.components_data_ = c.data.astype(np.float32)
        self.components_indices_ = c.indices.astype(np.int32)
        self.components_indptr_ = c.indptr.astype(np.int64 if c.nnz > np.iinfo(np.int32).max else np.int32)
        self.components_shape_ = np.array(c.shape, dtype=np.int64)

    def components(self):
        """The (n_components_, n_features_in_) CSR projection matrix."""
        import scipy.sparse as sp

        cache = getattr(self, "_csr_cache", None)
        if cache is None or cache[0] is not self.components_data_:
            c = sp.csr_matrix((self.components_data_, self.components_indices_, self.components_indptr_),
                              shape=tuple(int(s) for s in self.components_shape_))
            cache = (self.components_data_, c)
            self._csr_cache = cache
        return cache[1]

    def _transform(self, x):
        return np.asarray(self.components() @ x.T).T

    def _expected_shapes(self):
        nnz = len(self.components_data_)
        return {"components_indices_": (nnz,), "components_indptr_": (self.n_components_ + 1,),
                "components_shape_": (2,)}


class GaussianRandomProjectionCompressor(Compressor):
    KIND = "grp"
    ARRAYS = ("components_",)

    def _fit(self, x):
        from sklearn.random_projection import GaussianRandomProjection

        self._cap({"asked": int(self.n_components), "features": x.shape[1]})
        rp = GaussianRandomProjection(n_components=self.n_components_, random_state=self.seed).fit(x)
        self.components_ = np.asarray(rp.components_, dtype=np.float32)

    def _transform(self, x):
        return x @ self.components_.T

    def _expected_shapes(self):
        return {"components_": (self.n_components_, self.n_features_in_)}


class IdentityCompressor(Compressor):
    """The uncompressed baseline: every feature kept, nothing stored."""

    KIND = "none"

    def _fit(self, x):
        self.n_components_, self.cap_reason_ = int(x.shape[1]), "uncompressed"

    def _transform(self, x):
        return x.copy()


_CLASSES: dict[str, type[Compressor]] = {c.KIND: c for c in (
    IncrementalPCACompressor, KernelPCACompressor, SparseRandomProjectionCompressor,
    GaussianRandomProjectionCompressor, IdentityCompressor)}
assert tuple(_CLASSES) == METHODS


def make_compressor(method: str, n_components: int = 128, *, seed: int = 0) -> Compressor:
    if method not in _CLASSES:
        raise ValueError(f"unknown compression method {method!r}; choose one of {', '.join(METHODS)}")
    return _CLASSES[method](n_components, seed=seed)


def load_compressor(path) -> Compressor:
    """A compressor saved by `Compressor.save`, of whichever kind the file holds."""
    path = Path(path)
    fix = f"point to a file written by Compressor.save (kinds: {', '.join(METHODS)})"
    try:
        z = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(f"{path}: no such compressor file", [Problem(str(path), "does not exist", fix=fix)]) from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: not a compressor file",
                         [Problem(str(path), f"not a readable npz ({e})", fix=fix)]) from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: not a compressor file", [Problem(str(path), "a single .npy array", fix=fix)])
    with z:
        kind = str(z["kind"]) if "kind" in z.files and z["kind"].ndim == 0 else ""
        if kind not in _CLASSES:
            raise InputError(f"{path}: not a compressor file",
                             [Problem(str(path), f"holds '{kind or 'unknown'}'", fix=fix)])
        try:
            return _CLASSES[kind]._from_npz(z, path)
        except (KeyError, ValueError, TypeError) as e:
            raise InputError(f"{path}: damaged {kind} compressor file",
                             [Problem(str(path), str(e), fix="save the compressor again")]) from None
