"""IPA and RPA descriptors from a detector's outputs: numpy only, shared by `extract` (torch) and the
runtime (ONNX), so that the database and a robot's camera image are described by one implementation.

- IPA: the stride-16 map (cropped to the image) pooled over positions, l2-normalised: summed (`sum`, the
  paper's; the default) or by generalized mean (`gem`, Radenovic et al.: the map clamped at 1e-6, mean of
  x^p, ^(1/p)), as `retrieval.pooling` / `retrieval.gem_p` say; recorded as `ipa_pooling` / `gem_p` in
  the extraction's, the index's and the bundle's describer.json (absent: `sum`).
- RPA: per region, each channel's maximum over the map cells the box touches, l2-normalised. Regions:
  the `rpa_proposals` best RPN proposals, then the detections scoring at least `rpa_min_score`.

The map is the detector's, or that of the retrieval backbone (`retrieval.backbone`,
`pipeline.retrieval.backbones`), computed on the original image at its own stride; with a
place-recognition head the IPA is the head's output (`global_descriptor`) instead of the pooled map
(the pooling is then ignored).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.retrieval.whitening import l2_normalize

POOLINGS = ("sum", "gem")
GEM_P = 3.0


def ipa_descriptor(feature_map: np.ndarray, pooling: str = "sum", p: float = GEM_P) -> np.ndarray:
    """(C,) float32 of a (C, h, w) map, l2-normalised: `sum` over positions (in float32, or float64 for a
    float64 map), or `gem`, the generalized mean (Radenovic et al.) of the map clamped at 1e-6 (a Lite
    trunk's linear bottleneck has negative activations), computed in float64: (mean of x^p)^(1/p); p = 1
    is mean pooling, a large p approaches max pooling."""
    if pooling == "sum":
        x = np.asarray(feature_map)
        return l2_normalize(x.astype(np.float64 if x.dtype == np.float64 else np.float32, copy=False).sum(axis=(1, 2)))
    if pooling == "gem":
        x = np.asarray(feature_map, dtype=np.float64)
        x = x.reshape(x.shape[0], -1)
        return l2_normalize(np.mean(np.maximum(x, 1e-6) ** p, axis=1) ** (1.0 / p))
    raise ValueError(f"pooling must be one of {POOLINGS}, got '{pooling}'")


def pooling_record(pooling: str, p: float) -> dict:
    """How the IPA pools the map, as report.json and describer.json record it: `ipa_pooling`, and `gem_p`
    with `gem` only."""
    return {"ipa_pooling": pooling, **({"gem_p": float(p)} if pooling == "gem" else {})}


def recorded_pooling(record: dict | None) -> tuple[str, float | None]:
    """(pooling, p) of a report.json or describer.json (`pooling_record`); p is None for `sum`. A record
    without the keys (written before pooling could be chosen) is `sum`."""
    pooling = (record or {}).get("ipa_pooling", "sum")
    return pooling, (float((record or {}).get("gem_p", GEM_P)) if pooling == "gem" else None)


def pooling_label(pooling: str, p: float | None) -> str:
    return f"gem (p {p})" if pooling == "gem" else pooling


def pooling_sets(pooling: str, p: float | None) -> str:
    """The `--set` options that pool as (`pooling`, `p`)."""
    return f"--set retrieval.pooling={pooling}" + (f" --set retrieval.gem_p={p}" if pooling == "gem" else "")


def check_pooling(report: Path, pooling: str, p: float) -> None:
    """Refuse to describe images for the extraction or index whose `report` (report.json) records another
    IPA pooling than (`pooling`, `p`): its database would be compared with descriptors pooled otherwise."""
    from pipeline.errors import InputError, Problem

    report = Path(report)
    want = recorded_pooling(json.loads(report.read_text()) if report.is_file() else None)
    have = (pooling, float(p) if pooling == "gem" else None)
    if want != have:
        raise InputError(f"{report.parent}: its IPA was pooled otherwise than this run would pool it", [Problem(
            str(report), f"extracted with retrieval.pooling {pooling_label(*want)}; this run pools "
            f"{pooling_label(*have)}", fix=pooling_sets(*want))])


def region_max(fmap: np.ndarray, boxes: np.ndarray, stride: float) -> np.ndarray:
    """(K, C): per box (pixels of the image the map was computed on), each channel's maximum over the
    cells the box touches.

    A cell [k * stride, (k + 1) * stride) is touched when the box overlaps it; boxes are clipped to the
    map (which covers the image, not the padding), and a box too thin to cover a cell still gets one.
    """
    fmap = np.asarray(fmap)
    h, w = fmap.shape[-2:]
    out = np.empty((len(np.asarray(boxes).reshape(-1, 4)), fmap.shape[0]), dtype=np.float32)
    for k, (x1, y1, x2, y2) in enumerate(np.asarray(boxes, dtype=np.float64).reshape(-1, 4)):
        c0 = min(max(int(np.floor(x1 / stride)), 0), w - 1)
        r0 = min(max(int(np.floor(y1 / stride)), 0), h - 1)
        c1 = min(max(int(np.ceil(x2 / stride)), c0 + 1), w)
        r1 = min(max(int(np.ceil(y2 / stride)), r0 + 1), h)
        out[k] = fmap[:, r0:r1, c0:c1].max(axis=(1, 2))
    return out


@dataclass
class ImageDescriptors:
    ipa: np.ndarray  # (C,) l2-normalised sum or GeM pooling (or a head's output)
    boxes: np.ndarray  # (K, 4) regions in original pixels: proposals first, then detections
    meta: list[tuple[str, float, int]]  # (source, score, class id) per region
    rpa: np.ndarray  # (K, C) l2-normalised region max pooling

    def query_rows(self, n: int) -> np.ndarray:
        """The regions a query matches when re-ranking: detections first (by score), then proposals."""
        from pipeline.retrieval.search import query_region_order

        return query_region_order([m[0] for m in self.meta], [m[1] for m in self.meta], n)


def describe_outputs(feature_map: np.ndarray, scale: tuple[float, float], stride: float, proposals: np.ndarray,
                     proposal_scores: np.ndarray, boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, *,
                     rpa_proposals: int, rpa_min_score: float, global_descriptor: np.ndarray | None = None,
                     pooling: str = "sum", gem_p: float = GEM_P) -> ImageDescriptors:
    """Descriptors of one image from the detector's outputs: the cropped (C, h, w) map, `scale` (the map's
    image over the original, y then x), and proposals / detections in original pixels; the IPA pools the
    map by `pooling` (`ipa_descriptor`). With a retrieval backbone, `feature_map` is its map (of the
    original image: scale 1, its stride) and `global_descriptor` a head's output, which is then the IPA
    (l2-normalised; `pooling` is ignored)."""
    top = np.argsort(-np.asarray(proposal_scores), kind="stable")[:rpa_proposals]
    keep = np.asarray(scores) >= rpa_min_score
    regions = np.vstack([np.asarray(proposals, np.float32).reshape(-1, 4)[top],
                         np.asarray(boxes, np.float32).reshape(-1, 4)[keep]]).astype(np.float32)
    meta = [("proposal", float(s), 0) for s in np.asarray(proposal_scores)[top]]
    meta += [("detection", float(s), int(c)) for s, c in zip(np.asarray(scores)[keep], np.asarray(labels)[keep],
                                                            strict=True)]
    sy, sx = scale
    pooled = region_max(feature_map, regions * np.float32([sx, sy, sx, sy]), stride)
    ipa = ipa_descriptor(feature_map, pooling, gem_p) if global_descriptor is None else l2_normalize(
        np.asarray(global_descriptor, dtype=np.float32).reshape(-1))
    return ImageDescriptors(ipa, regions, meta, l2_normalize(pooled))


def describe_graph_outputs(out, meta: dict, *, rpa_proposals: int, rpa_min_score: float) -> ImageDescriptors:
    """`describe_outputs` of the describer graph's outputs in order (`feature_map`, `proposals`,
    `proposal_scores`, `boxes`, `scores`, `labels`, then, when `meta` (describer.json) has a
    `retrieval_backbone`, its `backbone_map` and, with a head, `backbone_ipa`). The IPA pools as `meta`'s
    `ipa_pooling` / `gem_p` say (`recorded_pooling`: sum for a describer.json without them)."""
    pooling, p = recorded_pooling(meta)
    pool = {"pooling": pooling, "gem_p": GEM_P if p is None else p}
    rb = meta.get("retrieval_backbone")
    if rb is None:
        return describe_outputs(out[0], tuple(meta["scale"]), meta["stride"], *out[1:6], rpa_proposals=rpa_proposals,
                                rpa_min_score=rpa_min_score, **pool)
    return describe_outputs(out[6], (1.0, 1.0), rb["stride"], *out[1:6], rpa_proposals=rpa_proposals,
                            rpa_min_score=rpa_min_score, global_descriptor=out[7] if len(out) > 7 else None, **pool)
