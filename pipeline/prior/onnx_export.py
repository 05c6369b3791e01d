"""Seed 001's multi-layer encoder as ONNX for the runtime: camera image -> the three layers' vectors.

The antialiased resize to `input_size` x `input_size` has no ONNX operator; like the frame encoder's
(`pipeline.sequence.onnx_export`), it is two constant matrices holding torch's own resize's response to
unit impulses, so the graph reproduces it exactly. Export checks onnxruntime against the torch encoder on
site images and refuses (nothing written) a graph that differs by more than `tolerance`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import SitelocError


def export_prior_encoder(encoder, image_hw: tuple[int, int], path: Path, images: list, *,
                         tolerance: float = 1e-3) -> dict:
    """`encoder` (a MultiLayerEncoder) as ONNX: input "image" (3, H, W) in [0, 1], one output per layer."""
    import torch
    from torch import nn

    from pipeline.sequence.onnx_export import export_image_graph, image_graph, resize_matrices

    class Normalised(nn.Module):  # the encoder's l2 normalisation of each layer, inside the graph
        def __init__(self, model):
            super().__init__()
            self.model = model

        def forward(self, x):
            outs = self.model(x)
            if not encoder.normalize:
                return outs
            return tuple(o / torch.clamp(torch.linalg.vector_norm(o, dim=1, keepdim=True), min=1e-12) for o in outs)

    ry, rx = resize_matrices(image_hw, (encoder.input_size, encoder.input_size))
    graph = image_graph(Normalised(encoder.model.cpu().eval()), ry, rx, encoder.mean, encoder.std)
    export_image_graph(graph, image_hw, path, list(encoder.layers))
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
