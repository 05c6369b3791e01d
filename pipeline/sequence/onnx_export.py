"""The sequence LSTM as ONNX for the runtime: frame features (B, T, 1000) -> pooled descriptor (B, hidden).

Batch and sequence length are dynamic axes, so the runtime's ring buffer can be queried with however
many frames it holds. Export checks onnxruntime against torch on random inputs of several lengths and
refuses a graph that differs by more than `tolerance` (the figures are returned for the bundle's json).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from pipeline.errors import SitelocError


def load_sequence_model(model_dir: Path):
    """A trained `train-sequence` output as a torch module in eval mode (tensors only, strict)."""
    import json

    from safetensors.torch import load_file

    from pipeline.sequence.model import build_sequence_model

    cfg = json.loads((Path(model_dir) / "config.json").read_text())
    model = build_sequence_model(**cfg["builder"])
    model.load_state_dict(load_file(str(Path(model_dir) / "weights.safetensors")), strict=True)
    return model.eval(), cfg


def export_sequence_onnx(model, path: Path, *, in_dim: int, lengths=(1, 2, 6, 10), tolerance: float = 1e-4,
                         seed: int = 0) -> dict:
    import torch
    from torch import nn

    from pipeline.io.atomic import atomic_file

    class Describe(nn.Module):  # the descriptor only: the place classifier stays offline
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, frames):
            return self.model.describe(frames)

    graph = Describe().eval()
    example = torch.zeros(1, 6, in_dim)
    # The tracer's warnings (LSTM shape checks, batch size) are about what the parity check below measures.
    with atomic_file(path, "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, (example,), fh, opset_version=17, dynamo=False, input_names=["frames"],
                          output_names=["descriptor"], dynamic_axes={"frames": {0: "batch", 1: "length"},
                                                                     "descriptor": {0: "batch"}})
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    worst = {}
    for n in lengths:
        x = (rng.standard_normal((3, n, in_dim)) * 5).astype(np.float32)
        with torch.no_grad():
            ref = graph(torch.from_numpy(x)).numpy()
        got = session.run(None, {"frames": x})[0]
        worst[n] = float(np.max(np.abs(got - ref)))
    if max(worst.values()) > tolerance:
        Path(path).unlink()
        raise SitelocError(f"the sequence LSTM's ONNX graph differs from torch by {max(worst.values()):.2e} "
                           f"(tolerance {tolerance:g}) at lengths {worst}; nothing was written")
    return {"max_abs_by_length": {str(k): v for k, v in worst.items()}, "tolerance": tolerance}


def resize_matrices(image_hw: tuple[int, int], out_hw: tuple[int, int]):
    """(ry (h, H), rx (w, W)) with `ry @ image @ rx.T` equal to torch's antialiased bilinear resize to
    `out_hw`: the resize is separable, so each matrix is its response to unit impulses. (ONNX has no
    antialiased resize; two constant MatMuls reproduce it exactly.)"""
    import torch
    import torch.nn.functional as F

    (H, W), (h, w) = image_hw, out_hw
    with torch.no_grad():
        rx = F.interpolate(torch.eye(W)[None, None], size=(W, w), mode="bilinear", align_corners=False,
                           antialias=True)[0, 0].T.contiguous()
        ry = F.interpolate(torch.eye(H)[None, None], size=(h, H), mode="bilinear", align_corners=False,
                           antialias=True)[0, 0].contiguous()
    return ry, rx


def resampling_matrices(image_hw: tuple[int, int], size: int):
    """`resize_matrices` for `FrameEncoder.prepare`'s resize: the shorter side to `size`, aspect kept."""
    H, W = image_hw
    s = size / min(H, W)
    return resize_matrices(image_hw, (max(1, round(H * s)), max(1, round(W * s))))


def image_graph(body, ry, rx, mean, std):
    """A module: camera image (3, H, W) in [0, 1] -> resized (matrices), normalised, a batch of one ->
    `body` (an nn.Module) -> its output(s) without the batch axis."""
    import torch
    from torch import nn

    class ImageGraph(nn.Module):
        def __init__(self):
            super().__init__()
            self.body = body
            self.register_buffer("ry", ry)
            self.register_buffer("rx", rx)
            self.register_buffer("mean", mean.cpu())
            self.register_buffer("std", std.cpu())

        def forward(self, image):
            x = torch.matmul(self.ry, torch.matmul(image, self.rx.T))[None]
            out = self.body((x - self.mean) / self.std)
            return tuple(o[0] for o in out) if isinstance(out, tuple) else out[0]

    return ImageGraph().eval()


def export_image_graph(graph, image_hw: tuple[int, int], path: Path, output_names: list[str]) -> None:
    """`graph` traced at the camera's size to ONNX at `path` (atomically)."""
    import torch

    from pipeline.io.atomic import atomic_file

    # The tracer's warnings (shapes taken as constants) are about what the parity checks measure.
    with atomic_file(path, "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, (torch.zeros(3, *image_hw),), fh, opset_version=17, dynamo=False,
                          input_names=["image"], output_names=output_names)


def export_frame_encoder(encoder, image_hw: tuple[int, int], path: Path, images: list, *,
                         tolerance: float = 5e-3) -> dict:
    """The frame encoder (camera image (3, H, W) in [0, 1] -> 1000 logits) as ONNX for the runtime, checked
    on `images` against `encoder` itself; refused (nothing written) beyond `tolerance` (absolute, logits)."""
    ry, rx = resampling_matrices(image_hw, encoder.size)
    graph = image_graph(encoder.model.cpu().eval(), ry, rx, encoder.mean, encoder.std)
    export_image_graph(graph, image_hw, path, ["logits"])
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for im in images:
        ref = encoder([im.cpu()])[0]
        got = session.run(None, {"image": im.cpu().numpy().astype(np.float32)})[0]
        worst = max(worst, float(np.max(np.abs(got - ref))))
    if worst > tolerance:
        Path(path).unlink()
        raise SitelocError(f"the frame encoder's ONNX graph differs from torch by {worst:.2e} on {len(images)} "
                           f"images (tolerance {tolerance:g}); nothing was written")
    return {"image_hw": list(image_hw), "frame_size": encoder.size, "weights": encoder.source, "dim": 1000,
            "parity": {"images": len(images), "max_abs": worst, "tolerance": tolerance}}
