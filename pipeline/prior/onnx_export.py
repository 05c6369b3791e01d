"""Seed 001's multi-layer encoder as ONNX for the runtime: camera image -> the three layers' vectors.

The antialiased resize to `input_size` x `input_size` has no ONNX operator; like the frame encoder's
(`pipeline.sequence.onnx_export`), it is two constant matrices holding torch's own resize's response to
unit impulses, so the graph reproduces it exactly. Export checks onnxruntime against the torch encoder on
site images and refuses (nothing written) a graph that differs by more than `tolerance`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from pipeline.errors import SitelocError


def square_resampling(image_hw: tuple[int, int], size: int):
    """(ry (size, H), rx (size, W)) with `ry @ image @ rx.T` the antialiased bilinear resize to size x size."""
    import torch
    import torch.nn.functional as F

    H, W = image_hw
    with torch.no_grad():
        rx = F.interpolate(torch.eye(W)[None, None], size=(W, size), mode="bilinear", align_corners=False,
                           antialias=True)[0, 0].T.contiguous()
        ry = F.interpolate(torch.eye(H)[None, None], size=(size, H), mode="bilinear", align_corners=False,
                           antialias=True)[0, 0].contiguous()
    return ry, rx


def export_prior_encoder(encoder, image_hw: tuple[int, int], path: Path, images: list, *,
                         tolerance: float = 1e-3) -> dict:
    """`encoder` (a MultiLayerEncoder) as ONNX: input "image" (3, H, W) in [0, 1], one output per layer."""
    import torch
    from torch import nn

    from pipeline.io.atomic import atomic_file

    ry, rx = square_resampling(image_hw, encoder.input_size)

    class Encode(nn.Module):
        def __init__(self):
            super().__init__()
            self.model = encoder.model.cpu().eval()
            self.register_buffer("ry", ry)
            self.register_buffer("rx", rx)
            self.register_buffer("mean", encoder.mean.cpu())
            self.register_buffer("std", encoder.std.cpu())

        def forward(self, image):
            x = torch.matmul(self.ry, torch.matmul(image, self.rx.T))[None]
            outs = self.model((x - self.mean) / self.std)
            if encoder.normalize:
                outs = tuple(o / torch.clamp(torch.linalg.vector_norm(o, dim=1, keepdim=True), min=1e-12)
                             for o in outs)
            return tuple(o[0] for o in outs)

    graph = Encode().eval()
    with atomic_file(path, "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, (torch.zeros(3, *image_hw),), fh, opset_version=17, dynamo=False,
                          input_names=["image"], output_names=list(encoder.layers))
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = {name: 0.0 for name in encoder.layers}
    for im in images:
        ref = encoder([im.cpu()])
        got = session.run(None, {"image": im.cpu().numpy().astype(np.float32)})
        for name, g in zip(encoder.layers, got, strict=True):
            worst[name] = max(worst[name], float(np.max(np.abs(g - ref[name][0]))))
    if max(worst.values()) > tolerance:
        Path(path).unlink()
        raise SitelocError(f"the multi-layer encoder's ONNX graph differs from torch by {max(worst.values()):.2e} "
                           f"on {len(images)} images (tolerance {tolerance:g}, by layer {worst}); nothing was written")
    return {"image_hw": list(image_hw), "encoder": encoder.describe(),
            "parity": {"images": len(images), "max_abs_by_layer": worst, "tolerance": tolerance}}
