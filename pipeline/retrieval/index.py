"""First-stage indexes: the database images nearest a query's IPA descriptor (Euclidean distance).

- `exact`: numpy, one matrix product (`ExactIndex`); the default, exact at any size that fits in RAM.
- `faiss`: faiss's exact `IndexFlatL2` (the same answers, faster on large databases).
- `hnsw`: faiss's HNSW graph (`hnsw_m` links per node; `hnsw_ef_search` candidates kept while searching).
- `ivf_flat` / `ivf_pq`: an inverted file of `ivf_lists` k-means cells, `ivf_nprobe` of them visited, holding
  the vectors as they are or product-quantised to `pq_bytes` codes each (of 8 bits from 10^4 images up).
  With `refine` > 1, IVF-PQ returns the `refine * k` nearest by its codes re-sorted by their exact distance
  from the database's own vectors.

Parameters live in `retrieval.index_params` (`pipeline.config.IndexParams`). `build-index` saves an
approximate index beside the database (`ipa_index.faiss`, faiss's own binary format: no pickle), so a
runtime loading a bundle does not rebuild a graph of 10^6 nodes. Recall against exact search and the
latencies are measured by `benchmarks/scale.py` (docs/retrieval.md#large-databases).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

KINDS = ("exact", "faiss", "hnsw", "ivf_flat", "ivf_pq")
INDEX_FILE = "ipa_index.faiss"


class ExactIndex:
    """Brute-force Euclidean search: ||q - x||^2 = |x|^2 - 2 q.x + |q|^2, done as one product."""

    name = "exact"

    def __init__(self, vectors: np.ndarray):
        self.vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        self.sq = np.einsum("ij,ij->i", self.vectors, self.vectors)

    def __len__(self) -> int:
        return len(self.vectors)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(squared distances, indices), each (B, k), nearest first."""
        q = np.atleast_2d(np.asarray(queries, dtype=np.float32))
        k = min(k, len(self))
        d = self.sq[None, :] - 2.0 * q @ self.vectors.T + np.einsum("ij,ij->i", q, q)[:, None]
        part = np.argpartition(d, k - 1, axis=1)[:, :k] if k < len(self) else np.tile(np.arange(len(self)), (len(q), 1))
        dk = np.take_along_axis(d, part, axis=1)
        order = np.lexsort((part, dk), axis=1)  # by distance, ties by database order
        return np.take_along_axis(dk, order, axis=1), np.take_along_axis(part, order, axis=1)


def _faiss():
    try:
        import faiss
    except ImportError:
        from pipeline.errors import SitelocError

        raise SitelocError("retrieval.index other than exact needs faiss: pip install 'siteloc[faiss]' "
                           "(faiss-cpu)") from None
    return faiss


def auto_lists(n: int) -> int:
    """IVF cells for n vectors: 4 sqrt(n) (faiss's guideline), with at least 39 training points per cell."""
    return max(1, min(int(round(4 * math.sqrt(n))), n // 39))


def auto_pq_bytes(dim: int) -> int:
    """PQ code size: the largest divisor of `dim` not above dim / 2 (faiss needs one sub-quantiser per byte
    dividing the dimension; 112-d: 56 bytes, an eighth of the float vector)."""
    return max(m for m in range(1, max(dim // 2, 1) + 1) if dim % m == 0)


def pq_bits(n: int) -> int:
    """Bits per PQ code: 8 (256 centroids per sub-quantiser), fewer below 39 x 256 vectors to train them on
    (faiss's minimum of 39 points per centroid), at least 1."""
    return int(min(8, max(1, math.floor(math.log2(max(n, 2) / 39))))) if n < 39 * 256 else 8


class FaissIndex:
    """A faiss index of `kind` (see the module) over (N, D) vectors; `params` as `IndexParams` (or None)."""

    name = "faiss"

    def __init__(self, vectors: np.ndarray, kind: str = "faiss", params=None, *, index=None):
        faiss = _faiss()
        if kind not in KINDS[1:]:
            raise ValueError(f"unknown faiss index kind '{kind}' (one of {KINDS[1:]})")
        from pipeline.config import IndexParams

        self.kind, self.params = kind, params or IndexParams()
        self.vectors = vectors  # the database's own (maybe memory-mapped) vectors: IVF-PQ's refinement reads them
        self.n, dim = int(vectors.shape[0]), int(vectors.shape[1])
        if index is not None:  # read from a file
            self.index = index
        else:
            self.index = self._build(faiss, np.ascontiguousarray(vectors, dtype=np.float32), dim)
        self._configure()

    def _build(self, faiss, v: np.ndarray, dim: int):
        p = self.params
        if self.kind == "faiss":
            index = faiss.IndexFlatL2(dim)
        elif self.kind == "hnsw":
            index = faiss.IndexHNSWFlat(dim, p.hnsw_m)
            index.hnsw.efConstruction = p.hnsw_ef_construction
        else:
            lists = p.ivf_lists or auto_lists(len(v))
            quantizer = faiss.IndexFlatL2(dim)
            if self.kind == "ivf_flat":
                index = faiss.IndexIVFFlat(quantizer, dim, lists)
            else:
                m = p.pq_bytes or auto_pq_bytes(dim)
                if dim % m:
                    from pipeline.errors import ConfigError

                    raise ConfigError(f"retrieval.index_params.pq_bytes {m} does not divide the descriptor's {dim} "
                                      f"dimensions; use a divisor (or null for {auto_pq_bytes(dim)})")
                index = faiss.IndexIVFPQ(quantizer, dim, lists, m, pq_bits(len(v)))
            index.cp.seed = p.seed
            # k-means on a seeded sample: faiss itself warns above 256 points per cell and gains nothing
            take = min(len(v), 256 * lists)
            sample = v if take == len(v) else v[np.sort(np.random.default_rng(p.seed).choice(len(v), take,
                                                                                           replace=False))]
            index.train(sample)
        index.add(v)
        return index

    def _configure(self) -> None:
        if self.kind == "hnsw":
            self.index.hnsw.efSearch = self.params.hnsw_ef_search
        elif self.kind in ("ivf_flat", "ivf_pq"):
            self.index.nprobe = min(self.params.ivf_nprobe, self.index.nlist)

    def __len__(self) -> int:
        return self.n

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(squared distances, indices), each (B, k), nearest first; -1 where fewer than k were found."""
        q = np.ascontiguousarray(np.atleast_2d(queries), dtype=np.float32)
        k = min(k, self.n)
        if self.kind == "hnsw" and self.index.hnsw.efSearch < k:  # the beam must hold the list asked for
            self.index.hnsw.efSearch = k
        refine = self.params.refine if self.kind == "ivf_pq" else 1
        d, i = self.index.search(q, min(k * refine, self.n))
        if refine > 1:
            d, i = self._refine(q, i, k)
        return d, i

    def _refine(self, q: np.ndarray, cand: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest of each query's candidates by exact distance. faiss's IndexRefineFlat would keep a second
        copy of every vector in RAM; this reads only the candidates' rows of the database's own vectors."""
        out_d = np.full((len(q), k), np.inf, dtype=np.float32)
        out_i = np.full((len(q), k), -1, dtype=np.int64)
        for row, (qv, c) in enumerate(zip(q, cand, strict=True)):
            c = c[c >= 0]
            if not len(c):
                continue
            order = np.argsort(c, kind="stable")  # rows in file order: a memory map reads forwards
            x = np.asarray(self.vectors[c[order]], dtype=np.float32)
            dist = np.einsum("ij,ij->i", x - qv, x - qv)
            best = np.lexsort((c[order], dist))[:k]
            out_d[row, :len(best)], out_i[row, :len(best)] = dist[best], c[order][best]
        return out_d, out_i

    def save(self, path: Path) -> None:
        _faiss().write_index(self.index, str(path))

    @classmethod
    def load(cls, path: Path, vectors: np.ndarray, kind: str, params=None) -> FaissIndex:
        index = _faiss().read_index(str(path))
        if index.ntotal != len(vectors) or index.d != vectors.shape[1]:
            from pipeline.errors import InputError, Problem

            raise InputError(f"{path}: an index of {index.ntotal} x {index.d}-d vectors beside a database of "
                             f"{len(vectors)} x {vectors.shape[1]}",
                             [Problem(str(path), "the index was built for other descriptors",
                                      fix="re-run `siteloc build-index`")])
        return cls(vectors, kind, params, index=index)


def make_index(kind: str, vectors: np.ndarray, params=None):
    """The first-stage index of `kind` (KINDS) over the database's IPA vectors."""
    if kind == "exact":
        return ExactIndex(vectors)
    return FaissIndex(vectors, kind, params)
