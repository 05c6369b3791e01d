"""RPA re-ranking on a place set: the paper's second stage measured on photographs.

The detector (`siteloc train-detector`'s output) gives each image its regions (the `rpa_proposals` best
RPN proposals and the detections scoring at least `rpa_min_score`); each backbone's map is max-pooled over
them (`describe_outputs`, as `extract` does). A variant's first-stage ranking is then re-ranked on its Top-N
by region matching (`search.rerank`), the regions PCA-whitened on the database's unless the variant is
unwhitened (as `build-index` does).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Regions:
    rows: np.ndarray  # (M, C) l2-normalised region descriptors, grouped by image
    offsets: np.ndarray  # (N + 1,)
    query_rows: list[np.ndarray]  # per image, its rows a query matches (detections first), relative to the image


def describe_regions(det, backbones: dict, paths: list[Path], max_side: int | None, r, progress: bool = False
                     ) -> tuple[dict[str, Regions], float, dict[str, float]]:
    """({backbone name: Regions} of the images, seconds of the detector, {name: seconds of its map and
    pooling}): one detector pass per image, each backbone's map pooled over the detector's regions."""
    import time

    import torch

    from pipeline.detection.inference import detector_features
    from pipeline.progress import progress_bar
    from pipeline.retrieval.descriptors import describe_outputs
    from pipeline.retrieval.place_set import load_tensor

    per = {name: ([], [0], []) for name in backbones}
    det_s, bb_s = 0.0, dict.fromkeys(backbones, 0.0)
    for path in progress_bar(paths, desc="regions", unit="image", enabled=progress, leave=False):
        x = load_tensor(path, max_side)
        t0 = time.perf_counter()
        with torch.no_grad():
            (f,) = detector_features(det, [x])
        det_s += time.perf_counter() - t0
        for name, bb in backbones.items():
            t0 = time.perf_counter()
            ((fmap, _),) = bb.describe_maps([x])
            d = describe_outputs(fmap, (1.0, 1.0), bb.stride, f.proposals, f.proposal_scores, f.boxes, f.scores,
                                 f.labels, rpa_proposals=r.rpa_proposals, rpa_min_score=r.rpa_min_score)
            bb_s[name] += time.perf_counter() - t0
            rows, offsets, query = per[name]
            rows.append(d.rpa)
            offsets.append(offsets[-1] + len(d.rpa))
            query.append(d.query_rows(r.query_regions))
    regions = {name: Regions(np.concatenate(rows) if rows else np.zeros((0, 0), np.float32),
                             np.asarray(offsets, dtype=np.int64), query)
               for name, (rows, offsets, query) in per.items()}
    return regions, det_s, bb_s


def reranked(first: np.ndarray, db: Regions, queries: Regions, whiten: bool, top_n: int) -> np.ndarray:
    """(Q, D) rankings: each query's first `top_n` re-ranked by region matching, the rest as they were."""
    from pipeline.retrieval.search import Database, rerank
    from pipeline.retrieval.whitening import PCAWhitening

    db_rows, q_rows = db.rows, queries.rows
    if whiten and len(db_rows) > 2:
        w = PCAWhitening().fit(db_rows)
        db_rows, q_rows = w.transform(db_rows), w.transform(q_rows)
    n = len(db.offsets) - 1
    database = Database([str(i) for i in range(n)], np.zeros((n, 3)), np.zeros((n, 1), np.float32), db_rows,
                        db.offsets)
    out = np.array(first, copy=True)
    for i in range(len(first)):
        mine = q_rows[queries.offsets[i]:queries.offsets[i + 1]][queries.query_rows[i]]
        head, _ = rerank(database, first[i, :top_n], mine)
        out[i, : len(head)] = head
    return out
