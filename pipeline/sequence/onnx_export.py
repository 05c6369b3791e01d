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
