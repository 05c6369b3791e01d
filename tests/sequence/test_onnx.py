"""The sequence LSTM's ONNX graph: dynamic length and batch, equal to torch, refused when it is not."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import SitelocError
from pipeline.sequence.model import build_sequence_model
from pipeline.sequence.onnx_export import export_sequence_onnx


def test_onnx_matches_torch_at_every_length(tmp_path):
    import onnxruntime as ort
    import torch

    torch.manual_seed(0)
    model = build_sequence_model(40, 12, 7).eval()
    parity = export_sequence_onnx(model, tmp_path / "seq.onnx", in_dim=40, lengths=(1, 3, 6, 10))
    assert set(parity["max_abs_by_length"]) == {"1", "3", "6", "10"}
    assert max(parity["max_abs_by_length"].values()) <= 1e-4
    session = ort.InferenceSession(str(tmp_path / "seq.onnx"), providers=["CPUExecutionProvider"])
    x = np.random.default_rng(1).standard_normal((2, 8, 40)).astype(np.float32)  # a length never exported
    with torch.no_grad():
        ref = model.describe(torch.from_numpy(x)).numpy()
        # mean pooling over time: the descriptor of a sequence is the mean of the LSTM's outputs
        y, _ = model.lstm(model.norm(torch.from_numpy(x)))
    np.testing.assert_allclose(session.run(None, {"frames": x})[0], ref, atol=1e-5)
    np.testing.assert_allclose(ref, y.mean(dim=1).numpy(), atol=1e-6)


def test_a_graph_outside_the_tolerance_is_not_kept(tmp_path):
    model = build_sequence_model(10, 4, 3).eval()
    with pytest.raises(SitelocError, match="differs from torch"):
        export_sequence_onnx(model, tmp_path / "seq.onnx", in_dim=10, tolerance=-1.0)
    assert not (tmp_path / "seq.onnx").exists()
