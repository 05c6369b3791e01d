"""How seed 001 scores the (room, area) classes of a query's neighbours: correlations and Gaussians.

- Correlation re-scoring of the ball tree's k neighbours: Pearson's r of the query and a neighbour
  vector, or Spearman's (Pearson's r of their ranks, ties averaged). The paper's "correlation distance
  normalised to 0..1" is d = (1 - r) / 2; the similarity used is 1 - d = (1 + r) / 2.
- `ClassGaussians`: one Gaussian per class fitted on its database vectors. With 10-50 images a class in
  128 dimensions the sample covariance is singular, so it is shrunk towards sigma^2 I, sigma^2 being the
  within-class variance pooled over all classes at the first fit (fixed afterwards, so appending a class
  changes no other class), by Ledoit-Wolf's coefficient (or a fixed one). Fitted state is arrays only.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_solve, cholesky, solve_triangular
from scipy.stats import rankdata


def standardise(x: np.ndarray, *, ranks: bool) -> np.ndarray:
    """Rows centred and scaled to unit norm (of their ranks with `ranks`): r(a, b) is then a . b."""
    x = np.asarray(x, dtype=np.float64)
    if ranks:
        x = rankdata(x, axis=-1)
    x = x - x.mean(axis=-1, keepdims=True)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def correlation(q: np.ndarray, rows: np.ndarray, *, method: str) -> np.ndarray:
    """Pearson or Spearman r of query `q` (D,) with each of `rows` (k, D)."""
    if method not in ("pearson", "spearman"):
        raise ValueError(f"method must be pearson or spearman, got '{method}'")
    ranks = method == "spearman"
    return standardise(rows, ranks=ranks) @ standardise(q, ranks=ranks)


def similarity_from_r(r: np.ndarray) -> np.ndarray:
    """1 - the correlation distance normalised to [0, 1]."""
    return (1.0 + np.asarray(r)) / 2.0


class ClassGaussians:
    """Per-class Gaussians of D-dimensional vectors; `log_likelihood` scores a query under each."""

    def __init__(self, shrinkage: float | None = None):
        self.shrinkage = shrinkage

    def fit(self, x: np.ndarray, labels: np.ndarray, n_classes: int | None = None) -> ClassGaussians:
        x = np.asarray(x, dtype=np.float64)
        labels = np.asarray(labels, dtype=np.int64)
        c = int(n_classes if n_classes is not None else labels.max() + 1)
        resid = x - np.stack([x[labels == k].mean(axis=0) if np.any(labels == k) else np.zeros(x.shape[1])
                              for k in range(c)])[labels]
        # Pooled within-class variance: the scale a class with few images falls back on.
        self.sigma2_ = float(max(np.mean(resid**2), 1e-12))
        d = x.shape[1]
        self.mean_ = np.zeros((0, d))
        self.chol_ = np.zeros((0, d, d))
        self.logdet_ = np.zeros(0)
        self.alpha_ = np.zeros(0)
        self.count_ = np.zeros(0, dtype=np.int64)
        return self.update(x, labels, range(c))

    def update(self, x: np.ndarray, labels: np.ndarray, classes) -> ClassGaussians:
        """(Re)fit `classes` from their rows of `x` (all of them); others are left as they are."""
        from sklearn.covariance import ledoit_wolf_shrinkage

        x = np.asarray(x, dtype=np.float64)
        labels = np.asarray(labels, dtype=np.int64)
        classes = list(classes)
        d = x.shape[1]
        grow = max(classes, default=-1) + 1 - len(self.mean_)
        if grow > 0:
            self.mean_ = np.vstack([self.mean_, np.zeros((grow, d))])
            self.chol_ = np.concatenate([self.chol_, np.zeros((grow, d, d))])
            self.logdet_ = np.r_[self.logdet_, np.zeros(grow)]
            self.alpha_ = np.r_[self.alpha_, np.zeros(grow)]
            self.count_ = np.r_[self.count_, np.zeros(grow, dtype=np.int64)]
        for k in classes:
            rows = x[labels == k]
            if len(rows) == 0:
                raise ValueError(f"class {k} has no vectors")
            mean = rows.mean(axis=0)
            if len(rows) < 2:
                alpha, sample = 1.0, np.zeros((d, d))
            else:
                sample = np.cov(rows, rowvar=False, bias=True)
                alpha = (float(ledoit_wolf_shrinkage(rows - mean, assume_centered=True))
                         if self.shrinkage is None else float(self.shrinkage))
            cov = (1.0 - alpha) * sample + alpha * self.sigma2_ * np.eye(d)
            chol = cholesky(cov + 1e-9 * self.sigma2_ * np.eye(d), lower=True)
            self.mean_[k], self.chol_[k], self.alpha_[k], self.count_[k] = mean, chol, alpha, len(rows)
            self.logdet_[k] = 2.0 * np.sum(np.log(np.diag(chol)))
        return self

    def keep(self, classes: np.ndarray) -> ClassGaussians:
        """Only the classes where `classes` (a boolean mask) is True, renumbered in order; fitted as they were."""
        classes = np.asarray(classes, dtype=bool)
        for f in ("mean_", "chol_", "logdet_", "alpha_", "count_"):
            setattr(self, f, getattr(self, f)[classes])
        return self

    def covariance(self, k: int) -> np.ndarray:
        return self.chol_[k] @ self.chol_[k].T

    def log_likelihood(self, y: np.ndarray, classes=None) -> np.ndarray:
        """log N(y; mean_k, cov_k) for each k in `classes` (all by default)."""
        y = np.asarray(y, dtype=np.float64)
        ks = np.arange(len(self.mean_)) if classes is None else np.asarray(list(classes), dtype=np.int64)
        d = y.shape[-1]
        out = np.empty(len(ks))
        for i, k in enumerate(ks):
            z = solve_triangular(self.chol_[k], y - self.mean_[k], lower=True)
            out[i] = -0.5 * (z @ z + self.logdet_[k] + d * np.log(2.0 * np.pi))
        return out

    def mahalanobis2(self, y: np.ndarray, k: int) -> float:
        diff = np.asarray(y, dtype=np.float64) - self.mean_[k]
        return float(diff @ cho_solve((self.chol_[k], True), diff))

    FITTED = ("mean_", "chol_", "logdet_", "alpha_", "count_", "sigma2_")

    def arrays(self) -> dict[str, np.ndarray]:
        out = {f: np.asarray(getattr(self, f)) for f in self.FITTED}
        out["shrinkage"] = np.array(-1.0 if self.shrinkage is None else self.shrinkage)
        return out

    @classmethod
    def from_arrays(cls, z) -> ClassGaussians:
        s = float(z["shrinkage"])
        g = cls(None if s < 0 else s)
        for f in cls.FITTED:
            setattr(g, f, float(z[f]) if f == "sigma2_" else np.asarray(z[f]))
        return g


def softmax(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    e = np.exp(a - a.max())
    return e / e.sum()
