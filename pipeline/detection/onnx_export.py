"""The trained detector as one ONNX graph that gives the runtime everything IPA and RPA need.

Input `image`: (3, H, W) float32 in [0, 1] at the site camera's size (the graph is traced at that size:
EfficientNet's "same" padding and the resize are fixed then; the runtime refuses other sizes). Outputs:
`feature_map` (C, h, w) cropped to the image, `proposals` (P, 4) and `proposal_scores` (P,), `boxes`
(D, 4), `scores` (D,), `labels` (D,) int64, all boxes in original pixels. The runtime turns them into
descriptors with `pipeline.retrieval.descriptors.describe_outputs`, as `extract` does from torch, the IPA
pooled as the metadata's `ipa_pooling` / `gem_p` say (set by the caller: `extract`, `export`).

With a retrieval backbone other than the detector (`pipeline.retrieval.backbones`), the same graph also
runs that backbone on the original image: outputs `backbone_map` (C, h, w) and, with a NetVLAD / GeM head,
`backbone_ipa` (D,); the metadata gets `retrieval_backbone` (its record, stride, outputs) and the
descriptors pool that map (`pipeline.retrieval.descriptors.describe_graph_outputs`).

`check_parity` runs torch and onnxruntime on real images and compares the map, the detections and the
IPA / RPA descriptors (and the backbone's map, within `feature_map_abs` of its largest magnitude when that
is above 1, and its head's output); export fails when any difference exceeds its tolerance.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

OUTPUTS = ("feature_map", "proposals", "proposal_scores", "boxes", "scores", "labels")
# box_px: two boxes are the same box within this; matched: the share of torch's detections and regions
# that onnxruntime must give too (ties in score may reorder them, and move one across the top-N cut).
TOLERANCE = {"feature_map_abs": 1e-2, "descriptor_abs": 1e-3, "box_px": 0.5, "matched": 0.98}


class DescriberGraph(nn.Module):
    """Faster R-CNN up to its detections, plus the map and the scored proposals it keeps internally."""

    def __init__(self, model, stride: float, backbone=None):
        super().__init__()
        self.model, self.stride, self.backbone = model, stride, backbone

    def forward(self, image: torch.Tensor):
        from torchvision.models.detection.rpn import concat_box_prediction_layers
        from torchvision.models.detection.transform import resize_boxes

        m = self.model
        original = (int(image.shape[-2]), int(image.shape[-1]))
        batch, _ = m.transform([image])
        fmaps = m.backbone(batch.tensors)
        feats = list(fmaps.values())
        objectness, deltas = m.rpn.head(feats)
        anchors = m.rpn.anchor_generator(batch, feats)
        per_level = [o[0].numel() for o in objectness]
        objectness, deltas = concat_box_prediction_layers(objectness, deltas)
        decoded = m.rpn.box_coder.decode(deltas.detach(), anchors).view(len(anchors), -1, 4)
        proposals, proposal_scores = m.rpn.filter_proposals(decoded, objectness, batch.image_sizes, per_level)
        detections, _ = m.roi_heads(fmaps, proposals, batch.image_sizes)
        resized = batch.image_sizes[0]
        cells = (math.ceil(resized[0] / self.stride), math.ceil(resized[1] / self.stride))
        d = detections[0]
        out = (fmaps["0"][0, :, :cells[0], :cells[1]], resize_boxes(proposals[0], resized, original),
               proposal_scores[0], resize_boxes(d["boxes"], resized, original), d["scores"], d["labels"])
        if self.backbone is None:
            return out
        return out + tuple(t[0] for t in self.backbone(image[None]))


def backbone_outputs(backbone) -> list[str]:
    """The graph outputs a retrieval backbone adds (none for the detector's own map)."""
    if backbone is None:
        return []
    return ["backbone_map"] + (["backbone_ipa"] if backbone.head is not None else [])


def export_describer(det, image_hw: tuple[int, int], path: Path, backbone=None) -> dict:
    """Write the ONNX graph for images of `image_hw` (height, width); returns what the runtime needs.
    `backbone`: a `RetrievalBackbone` whose map the descriptors pool instead of the detector's."""
    from pipeline.detection.builders import STRIDE

    if backbone is not None:
        backbone = backbone.eval().cpu()
    graph = DescriberGraph(det.model.eval().cpu(), STRIDE, backbone).eval()
    example = torch.rand(3, *image_hw, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        batch, _ = det.model.transform([example])
    resized = batch.image_sizes[0]
    with warnings.catch_warnings():  # tracer notes on shapes fixed at the traced size: intended, see above
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, (example,), str(path), opset_version=17, dynamo=False, input_names=["image"],
                          output_names=[*OUTPUTS, *backbone_outputs(backbone)])
    meta = {"input": "image", "outputs": list(OUTPUTS), "image_hw": [int(v) for v in image_hw],
            "resized_hw": [int(v) for v in resized], "stride": float(STRIDE),
            "scale": [resized[0] / image_hw[0], resized[1] / image_hw[1]]}
    if backbone is not None:
        with torch.no_grad():
            map_hw = [int(v) for v in backbone(example[None])[0].shape[-2:]]
        meta["retrieval_backbone"] = {**backbone.record(), "outputs": backbone_outputs(backbone), "map_hw": map_hw}
    return meta


def _match_regions(a_boxes: np.ndarray, b_boxes: np.ndarray, tol: float) -> list[tuple[int, int]]:
    """Pairs (i, j) of boxes equal within `tol` pixels: tied proposal scores may list them in another order."""
    pairs, used = [], set()
    for i, box in enumerate(a_boxes):
        diff = np.abs(b_boxes - box).max(axis=1) if len(b_boxes) else np.zeros(0)
        for j in np.flatnonzero(diff <= tol):
            if j not in used:
                used.add(int(j))
                pairs.append((i, int(j)))
                break
    return pairs


def matched_share(pairs: list, boxes: np.ndarray) -> float:
    """The share of `boxes` that found a partner; 1 when there is nothing to find (no detections)."""
    return len(pairs) / len(boxes) if len(boxes) else 1.0


def check_parity(det, onnx_path: Path, meta: dict, images: list[torch.Tensor], *, rpa_proposals: int,
                 rpa_min_score: float, backbone=None) -> dict:
    """Largest torch-vs-onnxruntime differences over `images`; raises SitelocError beyond TOLERANCE.
    `backbone`: the retrieval backbone the graph was exported with (`export_describer`). Both sides'
    descriptors come from `describe_graph_outputs(…, meta)`, so the IPA is compared as `meta` pools it."""
    import onnxruntime as ort

    from pipeline.errors import SitelocError
    from pipeline.retrieval.descriptors import describe_graph_outputs

    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    if (backbone is None) != (meta.get("retrieval_backbone") is None):
        raise SitelocError("ONNX parity: the graph's metadata and the backbone given to check it disagree")
    graph = DescriberGraph(det.model.eval().cpu(), meta["stride"], None if backbone is None else backbone.cpu()).eval()
    names = [*OUTPUTS, *backbone_outputs(backbone)]
    worst = {"feature_map_abs": 0.0, "ipa_abs": 0.0, "rpa_abs": 0.0, "score_abs": 0.0, "detections_matched": 1.0,
             "regions_matched": 1.0}
    if backbone is not None:
        worst.update(backbone_map_abs=0.0, backbone_map_rel=0.0)
    for image in images:
        with torch.no_grad():
            ref = [t.numpy() for t in graph(image)]
        got = session.run(names, {"image": image.numpy()})
        if backbone is not None:
            if ref[6].shape != got[6].shape:
                raise SitelocError(f"ONNX export: the backbone maps differ in shape ({ref[6].shape} vs {got[6].shape})")
            diff = float(np.abs(ref[6] - got[6]).max())
            worst["backbone_map_abs"] = max(worst["backbone_map_abs"], diff)
            worst["backbone_map_rel"] = max(worst["backbone_map_rel"], diff / max(1.0, float(np.abs(ref[6]).max())))
        if ref[0].shape != got[0].shape or len(ref[3]) != len(got[3]):
            raise SitelocError(f"ONNX export: outputs differ in shape (map {ref[0].shape} vs {got[0].shape}, "
                               f"{len(ref[3])} vs {len(got[3])} detections)")
        worst["feature_map_abs"] = max(worst["feature_map_abs"], float(np.abs(ref[0] - got[0]).max()))
        pairs = _match_regions(ref[3], got[3], TOLERANCE["box_px"])  # near-equal scores may swap order
        worst["detections_matched"] = min(worst["detections_matched"], matched_share(pairs, ref[3]))
        if pairs:
            i, j = np.array(pairs).T
            worst["score_abs"] = max(worst["score_abs"], float(np.abs(ref[4][i] - got[4][j]).max()))
        a, b = (describe_graph_outputs(o, meta, rpa_proposals=rpa_proposals, rpa_min_score=rpa_min_score)
                for o in (ref, got))
        worst["ipa_abs"] = max(worst["ipa_abs"], float(np.abs(a.ipa - b.ipa).max()))
        pairs = _match_regions(a.boxes, b.boxes, TOLERANCE["box_px"])
        worst["regions_matched"] = min(worst["regions_matched"], matched_share(pairs, a.boxes))
        if pairs:
            i, j = np.array(pairs).T
            worst["rpa_abs"] = max(worst["rpa_abs"], float(np.abs(a.rpa[i] - b.rpa[j]).max()))
    failed = [k for k, limit in (("feature_map_abs", TOLERANCE["feature_map_abs"]),
                                 ("ipa_abs", TOLERANCE["descriptor_abs"]), ("rpa_abs", TOLERANCE["descriptor_abs"]),
                                 ("score_abs", TOLERANCE["descriptor_abs"]),
                                 ("backbone_map_rel", TOLERANCE["feature_map_abs"])) if worst.get(k, 0.0) > limit]
    failed += [k for k in ("detections_matched", "regions_matched") if worst[k] < TOLERANCE["matched"]]
    if failed:
        raise SitelocError(f"ONNX export: onnxruntime and torch disagree beyond tolerance on {failed}: {worst} "
                           f"(tolerances {TOLERANCE})")
    return {"images": len(images), "max_differences": worst, "tolerance": TOLERANCE}
