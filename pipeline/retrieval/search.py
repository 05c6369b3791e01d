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

from dataclasses import dataclass

import numpy as np

from pipeline.retrieval.index import ExactIndex, FaissIndex, make_index  # noqa: F401  (the first stage)


@dataclass
class Database:
    """Whitened database descriptors with poses; regions of image i are rpa[offsets[i]:offsets[i + 1]]."""

    image_ids: list[str]
    poses: np.ndarray  # (N, 3) x, y, theta in the map frame
    ipa: np.ndarray  # (N, D)
    rpa: np.ndarray  # (M, Dr)
    offsets: np.ndarray  # (N + 1,)

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


def rerank(db: Database, first: np.ndarray, query_regions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(final order, region score of each `first` entry): Top-N sorted by region score, ties by IPA rank."""
    scores = np.array([region_score(query_regions, db.regions(int(i))) for i in first])
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
