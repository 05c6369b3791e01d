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


def test_resampling_matrices_are_the_antialiased_resize():
    """ry @ image @ rx.T equals torch's antialiased bilinear resize (ONNX has none), at an odd size."""
    import torch
    import torch.nn.functional as F

    from pipeline.sequence.onnx_export import resampling_matrices

    image = torch.rand(3, 61, 83, generator=torch.Generator().manual_seed(0))
    ry, rx = resampling_matrices((61, 83), 24)
    want = F.interpolate(image[None], size=(24, 33), mode="bilinear", align_corners=False, antialias=True)[0]
    assert ry.shape == (24, 61) and rx.shape == (33, 83)
    torch.testing.assert_close(ry @ image @ rx.T, want, atol=1e-5, rtol=0)
    np.testing.assert_allclose(ry.sum(1).numpy(), 1.0, atol=1e-5)  # each output pixel a weighted mean


def test_square_resize_matrices_are_the_multilayer_encoders_resize():
    import torch

    from pipeline.descriptors.multilayer import MultiLayerEncoder
    from pipeline.sequence.onnx_export import resize_matrices

    image = torch.rand(3, 61, 83, generator=torch.Generator().manual_seed(1))
    ry, rx = resize_matrices((61, 83), (32, 32))
    want = MultiLayerEncoder("efficientnet_lite0", None, 32).prepare(image)
    torch.testing.assert_close(ry @ image @ rx.T, want, atol=1e-5, rtol=0)


def test_frame_encoder_onnx_matches_the_encoder_and_refuses_beyond_the_tolerance(tmp_path):
    import onnxruntime as ort
    import torch

    from pipeline.sequence.frames import FrameEncoder
    from pipeline.sequence.onnx_export import export_frame_encoder

    enc = FrameEncoder(None, 32)
    images = [torch.rand(3, 48, 64, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    meta = export_frame_encoder(enc, (48, 64), tmp_path / "frames.onnx", images)
    assert meta["parity"]["max_abs"] <= meta["parity"]["tolerance"] and meta["image_hw"] == [48, 64]
    session = ort.InferenceSession(str(tmp_path / "frames.onnx"), providers=["CPUExecutionProvider"])
    other = torch.rand(3, 48, 64, generator=torch.Generator().manual_seed(9))
    np.testing.assert_allclose(session.run(None, {"image": other.numpy()})[0], enc([other])[0], atol=1e-4)
    with pytest.raises(SitelocError, match="frame encoder"):
        export_frame_encoder(enc, (48, 64), tmp_path / "bad.onnx", images, tolerance=-1.0)
    assert not (tmp_path / "bad.onnx").exists()
