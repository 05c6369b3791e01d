"""Whitening of l2-normalised CNN descriptors, fitted on the database, saved as arrays.

- `PCAWhitening` (Jegou & Chum 2012; what the paper applies to IPA and RPA): centre, project on the
  principal axes, divide by the square root of each axis' variance, l2-normalise again. The output
  dimension is capped by what the data supports: at most min(n_components, n_samples - 1, n_features)
  axes, and only axes whose variance is above `rel_eps` times the largest (`cap_reason_` says which
  limit applied).
- `ShrinkageWhitening`: PCA whitening with the variances regularised by as much as the ratio of dimensions
  to samples calls for, so a small database cannot be over-whitened (docs/retrieval.md#whitening).
- `LearnedWhitening` (Radenovic, Tolias & Chum 2016, "Lw"): supervised, from pairs of descriptors known
  to show the same place (here: geo-tags within a distance and heading). The intra-pair scatter C_S is
  whitened away first (C_S^-1/2), then the whitened data's own covariance is diagonalised and its largest
  axes kept, so differences between views of one place shrink while differences between places keep
  their spread.

Both follow scikit-learn's conventions (hyperparameters in `__init__`, `fit` returns self, fitted state
ends in `_`) and save to / load from `.npz` without pickles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.atomic import atomic_file


def l2_normalize(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), eps)


class _Saved:
    """npz round trip of the fitted arrays and the hyperparameters (no pickles: allow_pickle=False)."""

    KIND = ""
    PARAMS: tuple[str, ...] = ()
    FITTED: tuple[str, ...] = ()

    def save(self, path: Path) -> Path:
        arrays = {f: np.asarray(getattr(self, f)) for f in self.FITTED}
        arrays["kind"] = np.array(self.KIND)
        for p in self.PARAMS:
            v = getattr(self, p)
            arrays[f"param_{p}"] = np.array(-1 if v is None else v)
        with atomic_file(Path(path), "wb") as fh:
            np.savez(fh, **arrays)
        return Path(path)

    @classmethod
    def load(cls, path: Path):
        from pipeline.errors import InputError, Problem

        with np.load(Path(path), allow_pickle=False) as z:
            kind = str(z["kind"]) if "kind" in z else ""
            if kind != cls.KIND:
                raise InputError(f"{path}: not a {cls.KIND} file",
                                 [Problem(str(path), f"holds '{kind or 'unknown'}'", fix="point to the right file")])
            params = {p: z[f"param_{p}"].item() for p in cls.PARAMS}
            obj = cls(**{k: (None if v == -1 else v) for k, v in params.items()})
            for f in cls.FITTED:
                setattr(obj, f, z[f].item() if z[f].ndim == 0 and z[f].dtype.kind in "iufU" else z[f])
        return obj


class PCAWhitening(_Saved):
    KIND = "pca_whitening"
    PARAMS = ("n_components", "rel_eps")
    FITTED = ("mean_", "components_", "explained_variance_", "n_components_", "cap_reason_")

    def __init__(self, n_components: int | None = None, rel_eps: float = 1e-6):
        self.n_components, self.rel_eps = n_components, rel_eps

    def fit(self, x: np.ndarray) -> PCAWhitening:
        x = np.asarray(x, dtype=np.float64)
        n, d = x.shape
        if n < 2:
            raise ValueError(f"whitening needs at least 2 descriptors, got {n}")
        self.mean_ = x.mean(axis=0)
        _, s, vt = np.linalg.svd(x - self.mean_, full_matrices=False)
        var = s**2 / (n - 1)
        supported = int(np.sum(var > self.rel_eps * var[0]))
        limits = {"asked": self.n_components or d, "samples - 1": n - 1, "features": d,
                  "non-degenerate axes": supported}
        self.cap_reason_ = min(limits, key=lambda k: (limits[k], k != "asked"))
        self.n_components_ = int(limits[self.cap_reason_])
        self.components_ = vt[: self.n_components_].astype(np.float32)
        self.explained_variance_ = var[: self.n_components_].astype(np.float32)
        self.mean_ = self.mean_.astype(np.float32)
        return self

    def transform(self, x: np.ndarray, *, normalize: bool = True) -> np.ndarray:
        y = (np.asarray(x, dtype=np.float32) - self.mean_) @ self.components_.T / np.sqrt(self.explained_variance_)
        return l2_normalize(y) if normalize else y


class ShrinkageWhitening(_Saved):
    """PCA whitening with every axis' variance raised by `regularization` times the mean variance before
    dividing: axes the database estimates well are whitened, axes it cannot estimate (a few images in many
    dimensions) are left nearly as they are instead of being blown up. With `regularization` None it is
    chosen from the data: `per_dimension` x dimensions / (samples - 1), large for a small database (close
    to the identity after centring) and small for a large one (close to PCA whitening). Every dimension
    is kept."""

    KIND = "shrinkage_whitening"
    PARAMS = ("regularization", "per_dimension")
    FITTED = ("mean_", "projection_", "regularization_", "n_components_", "cap_reason_")

    def __init__(self, regularization: float | None = None, per_dimension: float = 10.0):
        self.regularization, self.per_dimension = regularization, per_dimension

    def fit(self, x: np.ndarray) -> ShrinkageWhitening:
        x = np.asarray(x, dtype=np.float64)
        n, d = x.shape
        if n < 2:
            raise ValueError(f"whitening needs at least 2 descriptors, got {n}")
        mean = x.mean(axis=0)
        w, v = np.linalg.eigh((x - mean).T @ (x - mean) / (n - 1))
        w = np.maximum(w, 0.0)
        rho = self.per_dimension * d / (n - 1) if self.regularization is None else float(self.regularization)
        eps = rho * max(w.mean(), 1e-12)
        self.mean_ = mean.astype(np.float32)
        # the symmetric (ZCA) form: with much regularisation the projection tends to the identity itself
        self.projection_ = ((v * (np.sqrt(w.mean() + eps) / np.sqrt(w + eps))) @ v.T).astype(np.float32)
        self.regularization_ = float(rho)
        self.n_components_ = d
        self.cap_reason_ = "features"
        return self

    def transform(self, x: np.ndarray, *, normalize: bool = True) -> np.ndarray:
        y = (np.asarray(x, dtype=np.float32) - self.mean_) @ self.projection_.T
        return l2_normalize(y) if normalize else y


class LearnedWhitening(_Saved):
    KIND = "learned_whitening"
    PARAMS = ("n_components", "rel_eps")
    FITTED = ("mean_", "projection_", "n_components_", "cap_reason_")

    def __init__(self, n_components: int | None = None, rel_eps: float = 1e-6):
        self.n_components, self.rel_eps = n_components, rel_eps

    def fit(self, x: np.ndarray, pairs: np.ndarray) -> LearnedWhitening:
        """`pairs`: (P, 2) row indices of descriptors that show the same place."""
        x = np.asarray(x, dtype=np.float64)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        n, d = x.shape
        if len(pairs) < 2:
            raise ValueError(f"learned whitening needs matching pairs, got {len(pairs)}")
        self.mean_ = x[np.unique(pairs)].mean(axis=0)
        diff = x[pairs[:, 0]] - x[pairs[:, 1]]
        c_s = diff.T @ diff / len(pairs)
        w, v = np.linalg.eigh(c_s)
        keep = w > self.rel_eps * w.max()  # C_S^-1/2 on the axes the pairs span
        p1 = (v[:, keep] / np.sqrt(w[keep])).T
        z = (x - self.mean_) @ p1.T
        c_d = z.T @ z / max(n - 1, 1)
        w2, v2 = np.linalg.eigh(c_d)
        order = np.argsort(w2)[::-1]
        limits = {"asked": self.n_components or d, "samples - 1": n - 1, "features": d,
                  "non-degenerate axes": int(keep.sum())}
        self.cap_reason_ = min(limits, key=lambda k: (limits[k], k != "asked"))
        self.n_components_ = int(limits[self.cap_reason_])
        self.projection_ = (v2[:, order[: self.n_components_]].T @ p1).astype(np.float32)
        self.mean_ = self.mean_.astype(np.float32)
        return self

    def transform(self, x: np.ndarray, *, normalize: bool = True) -> np.ndarray:
        y = (np.asarray(x, dtype=np.float32) - self.mean_) @ self.projection_.T
        return l2_normalize(y) if normalize else y


def geo_pairs(xy: np.ndarray, theta: np.ndarray, group: np.ndarray, *, max_distance: float,
              max_heading_deg: float) -> np.ndarray:
    """(P, 2) index pairs i < j of images within `max_distance` metres and `max_heading_deg` of each other,
    taken at different stops (`group`), the positives `LearnedWhitening` learns from."""
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, dtype=np.float64)
    cand = cKDTree(xy).query_pairs(max_distance, output_type="ndarray")
    if len(cand) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    dth = np.abs(np.angle(np.exp(1j * (theta[cand[:, 0]] - theta[cand[:, 1]]))))
    ok = (dth <= np.radians(max_heading_deg)) & (np.asarray(group)[cand[:, 0]] != np.asarray(group)[cand[:, 1]])
    return np.sort(cand[ok], axis=1).astype(np.int64)
