"""IPA and RPA descriptors from a detector's outputs: numpy only, shared by `extract` (torch) and the
runtime (ONNX), so that the database and a robot's camera image are described by one implementation.

- IPA: the stride-16 map (cropped to the image) summed over positions, l2-normalised.
- RPA: per region, each channel's maximum over the map cells the box touches, l2-normalised. Regions:
  the `rpa_proposals` best RPN proposals, then the detections scoring at least `rpa_min_score`.

The map is the detector's, or that of the retrieval backbone (`retrieval.backbone`,
`pipeline.retrieval.backbones`), computed on the original image at its own stride; with a
place-recognition head the IPA is the head's output (`global_descriptor`) instead of the sum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.retrieval.whitening import l2_normalize


def ipa_descriptor(feature_map: np.ndarray) -> np.ndarray:
    """Sum pooling of a (C, h, w) map over positions, l2-normalised."""
    return l2_normalize(np.asarray(feature_map, dtype=np.float32).sum(axis=(1, 2)))


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
    ipa: np.ndarray  # (C,) l2-normalised sum pooling
    boxes: np.ndarray  # (K, 4) regions in original pixels: proposals first, then detections
    meta: list[tuple[str, float, int]]  # (source, score, class id) per region
    rpa: np.ndarray  # (K, C) l2-normalised region max pooling

    def query_rows(self, n: int) -> np.ndarray:
        """The regions a query matches when re-ranking: detections first (by score), then proposals."""
        from pipeline.retrieval.search import query_region_order

        return query_region_order([m[0] for m in self.meta], [m[1] for m in self.meta], n)


def describe_outputs(feature_map: np.ndarray, scale: tuple[float, float], stride: float, proposals: np.ndarray,
                     proposal_scores: np.ndarray, boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, *,
                     rpa_proposals: int, rpa_min_score: float,
                     global_descriptor: np.ndarray | None = None) -> ImageDescriptors:
    """Descriptors of one image from the detector's outputs: the cropped (C, h, w) map, `scale` (the map's
    image over the original, y then x), and proposals / detections in original pixels. With a retrieval
    backbone, `feature_map` is its map (of the original image: scale 1, its stride) and `global_descriptor`
    a head's output, which is then the IPA (l2-normalised)."""
    top = np.argsort(-np.asarray(proposal_scores), kind="stable")[:rpa_proposals]
    keep = np.asarray(scores) >= rpa_min_score
    regions = np.vstack([np.asarray(proposals, np.float32).reshape(-1, 4)[top],
                         np.asarray(boxes, np.float32).reshape(-1, 4)[keep]]).astype(np.float32)
    meta = [("proposal", float(s), 0) for s in np.asarray(proposal_scores)[top]]
    meta += [("detection", float(s), int(c)) for s, c in zip(np.asarray(scores)[keep], np.asarray(labels)[keep],
                                                            strict=True)]
    sy, sx = scale
    pooled = region_max(feature_map, regions * np.float32([sx, sy, sx, sy]), stride)
    ipa = ipa_descriptor(feature_map) if global_descriptor is None else l2_normalize(
        np.asarray(global_descriptor, dtype=np.float32).reshape(-1))
    return ImageDescriptors(ipa, regions, meta, l2_normalize(pooled))


def describe_graph_outputs(out, meta: dict, *, rpa_proposals: int, rpa_min_score: float) -> ImageDescriptors:
    """`describe_outputs` of the describer graph's outputs in order (`feature_map`, `proposals`,
    `proposal_scores`, `boxes`, `scores`, `labels`, then, when `meta` (describer.json) has a
    `retrieval_backbone`, its `backbone_map` and, with a head, `backbone_ipa`)."""
    rb = meta.get("retrieval_backbone")
    if rb is None:
        return describe_outputs(out[0], tuple(meta["scale"]), meta["stride"], *out[1:6], rpa_proposals=rpa_proposals,
                                rpa_min_score=rpa_min_score)
    return describe_outputs(out[6], (1.0, 1.0), rb["stride"], *out[1:6], rpa_proposals=rpa_proposals,
                            rpa_min_score=rpa_min_score, global_descriptor=out[7] if len(out) > 7 else None)
