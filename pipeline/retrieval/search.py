"""Two-stage retrieval (seed 000 section 3.1.2): IPA Top-N, RPA spatial re-ranking, weighted Top-K poses.

numpy only (the runtime imports this; no torch). Descriptors arrive whitened and l2-normalised.

1. First stage: the `top_n` database images nearest the query's IPA descriptor in Euclidean distance,
   through an index of `pipeline.retrieval.index` (exact by default; faiss's flat, HNSW or IVF for large ones).
2. Re-ranking: each of the Top-N is scored by region matching. The rule turning several query regions
   into one score: for every query region, its best match among the database image's regions (the
   largest cosine similarity, i.e. the smallest Euclidean distance between unit vectors, as the paper
   compares them); the image's score is the mean of those best matches over the query regions. The
   Top-N are then sorted by that score (ties keep the IPA order), so re-ranking is a permutation of them.
3. Candidates: the first K of the final order, with their poses and weights `candidate_weights`
   (4:3:2:1 normalised to sum to one).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

from pipeline.retrieval.index import ExactIndex, FaissIndex, make_index  # noqa: F401  (the first stage)


class ChunkedRows:
    """Several (n_k, D) arrays sliced as one (sum n_k, D) matrix, without joining them: the record batches of a
    memory-mapped region file. A slice within one array is a view of it; across arrays, a copy of its rows."""

    def __init__(self, chunks: list[np.ndarray]):
        self.chunks = list(chunks)
        self.starts = np.concatenate([[0], np.cumsum([len(c) for c in self.chunks])]).astype(np.int64)
        self.shape = (int(self.starts[-1]), int(self.chunks[0].shape[1]))
        self.dtype = self.chunks[0].dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: slice) -> np.ndarray:
        lo, hi, step = key.indices(self.shape[0])
        if step != 1:
            raise IndexError("ChunkedRows takes contiguous slices")
        hi = max(hi, lo)
        first = int(np.searchsorted(self.starts, lo, side="right")) - 1
        if first >= len(self.chunks) or hi <= self.starts[first + 1]:
            k = min(first, len(self.chunks) - 1)
            return self.chunks[k][lo - self.starts[k]:hi - self.starts[k]]
        last = int(np.searchsorted(self.starts, hi, side="left")) - 1
        return np.concatenate([self.chunks[k][max(lo, self.starts[k]) - self.starts[k]:
                                              min(hi, self.starts[k + 1]) - self.starts[k]]
                               for k in range(first, last + 1)])


def as_rows(chunks: list[np.ndarray]):
    """One array as it is; several as ChunkedRows."""
    return chunks[0] if len(chunks) == 1 else ChunkedRows(chunks)


@dataclass
class Database:
    """Whitened database descriptors with poses; regions of image i are rpa[offsets[i]:offsets[i + 1]]."""

    image_ids: list[str]
    poses: np.ndarray  # (N, 3) x, y, theta in the map frame
    ipa: np.ndarray  # (N, D)
    rpa: np.ndarray | ChunkedRows  # (M, Dr)
    offsets: np.ndarray  # (N + 1,)
    paged: bool = False  # rpa is memory-mapped from a file: re-ranking asks for the Top-N's pages at once

    def regions(self, i: int) -> np.ndarray:
        return self.rpa[self.offsets[i]:self.offsets[i + 1]]


def region_offsets(image_ids: list[str], region_image_ids: list[str]) -> np.ndarray:
    """(N + 1,) offsets of each image's regions in a region table grouped by image in `image_ids` order.

    Raises ValueError when the regions are not grouped that way (or name an unknown image)."""
    pos = {i: k for k, i in enumerate(image_ids)}
    owner = np.array([pos[i] for i in region_image_ids], dtype=np.int64)
    if np.any(np.diff(owner) < 0):
        raise ValueError("region rows are not grouped by image in the images' order")
    return np.searchsorted(owner, np.arange(len(image_ids) + 1))


def query_region_order(sources, scores, n: int) -> np.ndarray:
    """The regions a query matches when re-ranking, as indices: detections first, each kind by score
    (highest first, ties in table order), at most n."""
    sources, scores = np.asarray(sources), np.asarray(scores, dtype=np.float64)
    return np.lexsort((-scores, sources != "detection"))[:n]


@dataclass
class Retrieval:
    first: np.ndarray  # (top_n,) database indices in IPA order
    ranked: np.ndarray  # (top_n,) the final order (a permutation of `first`)
    region_scores: np.ndarray | None  # (top_n,) per `first` entry, None without re-ranking
    candidates: np.ndarray  # (K, 4) x, y, theta, weight


def region_score(query_regions: np.ndarray, db_regions: np.ndarray) -> float:
    """Mean over query regions of the best cosine similarity among the database image's regions."""
    if len(query_regions) == 0 or len(db_regions) == 0:
        return -1.0
    return float(np.mean(np.max(query_regions @ db_regions.T, axis=1)))


def will_need(arrays: list[np.ndarray]) -> int:
    """Ask the OS to start reading the pages of these memory-mapped arrays now, all at once (madvise
    MADV_WILLNEED: asynchronous read-ahead), so that touching them next waits for one disk round, not one per
    array. A no-op where the C library has no madvise. The standard library's mmap.madvise needs the mmap
    object, which numpy views of an Arrow memory map do not carry; so libc's, on their addresses. Returns the
    arrays the OS took the advice for."""
    libc = _libc()
    if libc is None:
        return 0
    taken = 0
    for a in arrays:
        if a.nbytes == 0:
            continue
        start = a.ctypes.data & ~(PAGE - 1)
        taken += libc.madvise(ctypes.c_void_p(start), ctypes.c_size_t(a.ctypes.data + a.nbytes - start),
                              MADV_WILLNEED) == 0
    return taken


PAGE, MADV_WILLNEED = 4096, 3  # Linux and macOS values
_LIBC: list = []


def _libc():
    if not _LIBC:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
            _LIBC.append(libc)
        except (OSError, AttributeError):
            _LIBC.append(None)
    return _LIBC[0]


def rerank(db: Database, first: np.ndarray, query_regions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(final order, region score of each `first` entry): Top-N sorted by region score, ties by IPA rank.
    A paged database first asks for all the Top-N's region pages at once (`will_need`)."""
    regions = [db.regions(int(i)) for i in first]
    if db.paged:
        will_need(regions)
    scores = np.array([region_score(query_regions, r) for r in regions])
    order = np.lexsort((np.arange(len(first)), -scores))
    return np.asarray(first)[order], scores


def weighted_candidates(poses: np.ndarray, weights) -> np.ndarray:
    """(K, 4) x, y, theta, weight: the first K = len(weights) poses (fewer if there are fewer), weights
    normalised."""
    k = min(len(weights), len(poses))
    w = np.asarray(weights[:k], dtype=np.float64)
    return np.column_stack([np.asarray(poses)[:k, :3], w / w.sum()])


def candidates_from(db: Database, ranked: np.ndarray, weights: tuple[float, ...]) -> np.ndarray:
    return weighted_candidates(db.poses[np.asarray(ranked)[: len(weights)]], weights)


def retrieve(db: Database, index, query_ipa: np.ndarray, query_regions: np.ndarray | None, *, top_n: int = 50,
             weights: tuple[float, ...] = (4, 3, 2, 1), rerank_regions: bool = True) -> Retrieval:
    _, idx = index.search(query_ipa[None, :], top_n)
    first = idx[0][idx[0] >= 0]
    if rerank_regions and query_regions is not None and len(query_regions):
        ranked, scores = rerank(db, first, query_regions)
    else:
        ranked, scores = first, None
    return Retrieval(first, ranked, scores, candidates_from(db, ranked, weights))
