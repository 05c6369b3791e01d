"""A trained detector as a feature extractor: what the descriptor and retrieval steps read from it.

`load_detector(model_dir)` rebuilds the network that `siteloc train-detector` wrote (its `config.json`
holds the builder arguments; the weights come from `weights.safetensors`, never from a pickle).

`detector_features(detector, images, boxes=...)` runs one forward pass over a batch and returns, per
image, everything seed 000 uses:

- `feature_map`: the stride-16 map the RPN and RoI heads see (for `vgg16` the output of the ReLU after
  conv5_3, i.e. conv5_3 rectified; the convolution's own output is overwritten by that in-place ReLU, so
  it is never read from a hook on the conv), cropped to the cells that cover the image rather than the
  batch padding: `ceil(h / 16) x ceil(w / 16)` of the resized image.
- `proposals`, `proposal_scores`: the RPN's post-NMS proposals (objectness probability), original pixels.
- `boxes`, `scores`, `labels`: the detections, original pixels, 1-based class ids.
- `box_features`: for the `boxes` argument (original pixels), max pooling of the map over each box: one
  vector per box, each channel's maximum over the cells the box touches (the paper's regional
  descriptor). Cells are taken as `floor(x1 / 16) .. ceil(x2 / 16)` of the cropped map, not with
  `roi_pool`'s rounded inclusive ends, which would let a box at the image border read a padding cell.
- `scale`: (sy, sx), resized / original size, so `original = resized / scale`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.errors import InputError, Problem


@dataclass
class TrainedDetector:
    model: torch.nn.Module
    classes: list[str]
    config: dict  # the training run's config.json
    device: torch.device


@dataclass
class ImageFeatures:
    feature_map: torch.Tensor  # (C, ceil(h/16), ceil(w/16)), float32, on CPU
    scale: tuple[float, float]  # (sy, sx): resized image size / original image size
    proposals: np.ndarray  # (P, 4) float32 x1, y1, x2, y2, original pixels
    proposal_scores: np.ndarray  # (P,) objectness probabilities
    boxes: np.ndarray  # (D, 4) detections, original pixels
    scores: np.ndarray  # (D,)
    labels: np.ndarray  # (D,) int64, 1-based class ids
    box_features: np.ndarray | None  # (K, C) RoI max pooled features of the given boxes


def pick_device(name: str = "auto") -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("device: CUDA was asked for but torch sees no GPU",
                         [Problem("--set detector.device", f"'{name}' is not available", fix="use auto or cpu")])
    return torch.device(name)


def load_detector(model_dir: Path, *, device: str = "auto") -> TrainedDetector:
    """The detector `siteloc train-detector` wrote to `model_dir`, in eval mode."""
    from safetensors.torch import load_file

    from pipeline.detection.builders import build_detector

    model_dir = Path(model_dir)
    cfg_path, weights_path = model_dir / "config.json", model_dir / "weights.safetensors"
    for p in (cfg_path, weights_path):
        if not p.is_file():
            raise InputError(f"{model_dir}: not a trained detector",
                             [Problem(str(p), "missing", fix="run `siteloc train-detector DATA --out DIR` first")])
    config = json.loads(cfg_path.read_text())
    built = build_detector(weights=None, **config["builder"])
    state = load_file(str(weights_path))
    try:
        built.model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise InputError(f"{weights_path}: does not fit the network in {cfg_path}",
                         [Problem(str(weights_path), str(exc).splitlines()[0],
                                  fix="retrain or restore the pair")]) from None
    dev = pick_device(device)
    return TrainedDetector(built.model.to(dev).eval(), list(config["classes"]), config, dev)


@torch.no_grad()
def detector_features(det: TrainedDetector, images: list[torch.Tensor], *,
                      boxes: list[np.ndarray] | None = None) -> list[ImageFeatures]:
    """One forward pass over `images` ((3, H, W) float tensors in [0, 1], sizes may differ)."""
    from torchvision.models.detection.rpn import concat_box_prediction_layers
    from torchvision.models.detection.transform import resize_boxes

    model = det.model
    originals = [tuple(int(v) for v in im.shape[-2:]) for im in images]
    batch, _ = model.transform([im.to(det.device) for im in images])
    fmaps = model.backbone(batch.tensors)
    # The RPN's forward returns boxes only; its own pieces also give the objectness scores.
    rpn = model.rpn
    feats = list(fmaps.values())
    objectness, deltas = rpn.head(feats)
    anchors = rpn.anchor_generator(batch, feats)
    per_level = [o[0].numel() for o in objectness]
    objectness, deltas = concat_box_prediction_layers(objectness, deltas)
    decoded = rpn.box_coder.decode(deltas.detach(), anchors).view(len(anchors), -1, 4)
    proposals, proposal_scores = rpn.filter_proposals(decoded, objectness, batch.image_sizes, per_level)
    detections, _ = model.roi_heads(fmaps, proposals, batch.image_sizes)
    fmap = fmaps["0"]
    stride = batch.tensors.shape[-1] / fmap.shape[-1]
    out = []
    for i, (orig, resized) in enumerate(zip(originals, batch.image_sizes, strict=True)):
        scale = (resized[0] / orig[0], resized[1] / orig[1])
        cells = (math.ceil(resized[0] / stride), math.ceil(resized[1] / stride))
        cropped = fmap[i, :, :cells[0], :cells[1]].float().cpu()
        box_features = None
        if boxes is not None:
            given = torch.as_tensor(np.asarray(boxes[i], dtype=np.float32).reshape(-1, 4))
            box_features = region_max(cropped, resize_boxes(given, orig, resized).numpy(), stride)
        d = detections[i]
        out.append(ImageFeatures(
            feature_map=cropped,
            scale=scale,
            proposals=resize_boxes(proposals[i], resized, orig).float().cpu().numpy(),
            proposal_scores=proposal_scores[i].float().cpu().numpy(),
            boxes=resize_boxes(d["boxes"], resized, orig).float().cpu().numpy(),
            scores=d["scores"].float().cpu().numpy(),
            labels=d["labels"].cpu().numpy().astype(np.int64),
            box_features=box_features,
        ))
    return out


def region_max(fmap: torch.Tensor, boxes: np.ndarray, stride: float) -> np.ndarray:
    """`pipeline.retrieval.descriptors.region_max` of a torch map (one implementation for torch and ONNX)."""
    from pipeline.retrieval.descriptors import region_max as region_max_np

    return region_max_np(fmap.detach().float().cpu().numpy(), boxes, stride)


def load_image(path: Path) -> torch.Tensor:
    """An image file as a (3, H, W) float tensor in [0, 1]; refused (InputError naming it) unless it decodes
    faithfully to 8-bit RGB."""
    from torchvision.transforms.functional import pil_to_tensor

    from pipeline.io.images import open_image

    return pil_to_tensor(open_image(path)).float() / 255.0
