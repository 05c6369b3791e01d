"""The runtime describer (`pipeline.runtime.describer`) on small hand-made ONNX graphs: the detector's
outputs alone, or with a retrieval backbone's map and head output (no detector needed)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.detection.onnx_export import OUTPUTS
from pipeline.runtime.bundle import BundleError
from pipeline.runtime.describer import OnnxDescriber


class FakeDescriber(nn.Module):
    """image (3, 48, 64) -> the describer graph's outputs: a stride-16 'detector' map, two proposals, one
    detection, and (with `backbone`) a stride-32 map and a 6-d head output."""

    def __init__(self, backbone: bool):
        super().__init__()
        self.backbone = backbone
        self.det = nn.Conv2d(3, 8, 16, stride=16)
        self.bb = nn.Conv2d(3, 5, 32, stride=32, padding=8)
        self.fc = nn.Linear(5, 6)
        self.register_buffer("props", torch.tensor([[0.0, 0.0, 30.0, 20.0], [20.0, 10.0, 63.0, 47.0]]))

    def forward(self, image):
        x = image[None]
        props = self.props + image.mean() * 0
        out = (self.det(x)[0], props, torch.stack([image.max(), image.mean()]), props[1:] - 2, image.max()[None],
               torch.ones(1, dtype=torch.int64))
        if not self.backbone:
            return out
        m = self.bb(x)
        return (*out, m[0], self.fc(m.amax((2, 3)))[0])


def _export(tmp_path, backbone: bool, **meta_extra):
    torch.manual_seed(0)
    net = FakeDescriber(backbone).eval()
    names = [*OUTPUTS, *(["backbone_map", "backbone_ipa"] if backbone else [])]
    image = torch.rand(3, 48, 64)
    with warnings.catch_warnings():  # the legacy exporter's deprecation notes, as in pipeline.detection.onnx_export
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (image,), str(tmp_path / "d.onnx"), opset_version=17, dynamo=False,
                          input_names=["image"], output_names=names)
    meta = {"image_hw": [48, 64], "scale": [1.0, 1.0], "stride": 16.0, "rpa_proposals": 2, "rpa_min_score": 0.3,
            **meta_extra}
    if backbone:
        meta["retrieval_backbone"] = {"name": "checkpoint", "stride": 32, "dim": 6,
                                      "outputs": ["backbone_map", "backbone_ipa"]}
    (tmp_path / "d.json").write_text(json.dumps(meta))
    with torch.no_grad():
        ref = [t.numpy() for t in net(image)]
    return image.numpy(), ref


def test_the_detectors_map_is_pooled_without_a_backbone(tmp_path):
    image, ref = _export(tmp_path, backbone=False)
    d = OnnxDescriber(tmp_path / "d.onnx", tmp_path / "d.json").describe(image)
    s = ref[0].sum(axis=(1, 2))
    np.testing.assert_allclose(d.ipa, s / np.linalg.norm(s), rtol=1e-5)
    assert d.rpa.shape == (3, 8)  # two proposals and the detection


def test_with_a_backbone_its_head_is_the_ipa_and_its_map_is_pooled_at_its_stride(tmp_path):
    image, ref = _export(tmp_path, backbone=True)
    runtime = OnnxDescriber(tmp_path / "d.onnx", tmp_path / "d.json")
    d = runtime.describe(image)
    assert runtime.backbone["stride"] == 32
    np.testing.assert_allclose(d.ipa, ref[7] / np.linalg.norm(ref[7]), rtol=1e-5, atol=1e-6)
    bb_map = ref[6]  # (5, 2, 2): the box (20, 10)-(63, 47) covers all four cells at 1/32
    want = bb_map.max(axis=(1, 2))
    np.testing.assert_allclose(d.rpa[1], want / np.linalg.norm(want), rtol=1e-5, atol=1e-6)
    first = bb_map[:, :1, :1].max(axis=(1, 2))  # (0, 0)-(30, 20): the first cell only
    np.testing.assert_allclose(d.rpa[0], first / np.linalg.norm(first), rtol=1e-5, atol=1e-6)
    with pytest.raises(BundleError, match="exported for 64 x 48"):
        runtime.describe(np.zeros((40, 64, 3), np.uint8))


def test_the_ipa_pools_as_describer_json_says(tmp_path):
    """`ipa_pooling: gem` (retrieval.pooling of the database's extraction): the generalized mean of the map; a
    describer.json without the key (an older bundle) sums; a pooling this runtime does not know is refused."""
    from pipeline.retrieval.descriptors import ipa_descriptor

    image, ref = _export(tmp_path, backbone=False, ipa_pooling="gem", gem_p=3.0)
    d = OnnxDescriber(tmp_path / "d.onnx", tmp_path / "d.json").describe(image)
    g = np.cbrt((np.maximum(ref[0], 1e-6).astype(np.float64) ** 3).mean(axis=(1, 2)))
    np.testing.assert_allclose(d.ipa, g / np.linalg.norm(g), rtol=1e-5)
    np.testing.assert_allclose(d.ipa, ipa_descriptor(ref[0], "gem"), rtol=1e-5)
    assert d.rpa.shape == (3, 8)
    for bad in ({"ipa_pooling": "max"}, {"ipa_pooling": "gem", "gem_p": 0}):
        (tmp_path / "d.json").write_text(json.dumps({**json.loads((tmp_path / "d.json").read_text()), **bad}))
        with pytest.raises(BundleError, match="not one this runtime pools with"):
            OnnxDescriber(tmp_path / "d.onnx", tmp_path / "d.json")


def test_a_describer_json_naming_outputs_the_graph_lacks_is_refused(tmp_path):
    _export(tmp_path, backbone=False)
    meta = json.loads((tmp_path / "d.json").read_text())
    meta["retrieval_backbone"] = {"stride": 32, "outputs": ["backbone_map"]}
    (tmp_path / "d.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match=r"lacks the outputs \['backbone_map'\]"):
        OnnxDescriber(tmp_path / "d.onnx", tmp_path / "d.json")


def test_an_image_file_is_decoded_by_the_shared_helper_and_a_damaged_one_named(tmp_path):
    """What `localize --bundle` hands the describer for each frame: a path. A frame that cannot be decoded is an
    InputError naming the file, not a PIL exception."""
    from PIL import Image

    from pipeline.errors import InputError
    from pipeline.runtime.describer import camera_image, image_array

    rgb = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "f.png")
    np.testing.assert_array_equal(image_array(tmp_path / "f.png"), image_array(rgb))
    data = (tmp_path / "f.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    Image.fromarray(np.zeros((48, 64), np.uint16)).save(tmp_path / "deep.png")
    for name, word in (("cut.png", "truncated"), ("deep.png", "16-bit")):
        with pytest.raises(InputError, match=word) as info:
            camera_image(tmp_path / name, (48, 64), "detector")
        assert str(tmp_path / name) in str(info.value)
