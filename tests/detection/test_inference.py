"""Feature access: shapes, the conv5_3 ReLU map, proposals and detections in original pixels, region max."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from pipeline.detection.builders import build_detector
from pipeline.detection.inference import detector_features, load_detector, region_max
from pipeline.errors import InputError

ARGS = {"backbone": "vgg16", "num_classes": 9, "min_size": 128, "max_size": 176, "anchor_sizes": [32, 64, 128],
        "rpn_post_nms_top_n_test": 50}


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    torch.manual_seed(0)
    built = build_detector(weights=None, **ARGS)
    d = tmp_path_factory.mktemp("det")
    save_file({k: v.contiguous() for k, v in built.model.state_dict().items()}, str(d / "weights.safetensors"))
    (d / "config.json").write_text(json.dumps({"builder": ARGS, "classes": [f"c{i}" for i in range(8)]}))
    return d


def test_maps_proposals_and_detections_match_torchvision_in_original_pixels(model_dir):
    det = load_detector(model_dir, device="cpu")
    torch.manual_seed(1)
    images = [torch.rand(3, 240, 320), torch.rand(3, 300, 200)]  # different sizes: one is padded
    hooked = []
    relu = det.model.backbone.body[29]
    assert isinstance(relu, torch.nn.ReLU)  # the ReLU after conv5_3 (features[28])
    handle = relu.register_forward_hook(lambda m, i, o: hooked.append(o.detach().clone()))
    feats = detector_features(det, images, boxes=[np.array([[0, 0, 320, 240], [40, 30, 120, 200]]),
                                                  np.zeros((0, 4))])
    handle.remove()
    with torch.no_grad():
        reference = det.model(images)  # torchvision's own path, postprocessed to original pixels
    for k, (im, f, ref) in enumerate(zip(images, feats, reference, strict=True)):
        h, w = im.shape[-2:]
        sy, sx = f.scale
        rh, rw = round(h * sy), round(w * sx)
        assert f.feature_map.shape == (512, math.ceil(rh / 16), math.ceil(rw / 16))
        assert torch.equal(f.feature_map, hooked[0][k, :, : f.feature_map.shape[1], : f.feature_map.shape[2]])
        assert (f.feature_map >= 0).all()  # rectified
        np.testing.assert_allclose(f.boxes, ref["boxes"].numpy(), rtol=1e-5, atol=1e-3)
        np.testing.assert_array_equal(f.labels, ref["labels"].numpy())
        assert len(f.proposals) == len(f.proposal_scores) <= 50
        assert (f.proposals[:, 2] <= w + 1e-3).all() and (f.proposals[:, 3] <= h + 1e-3).all()
        assert ((f.proposal_scores >= 0) & (f.proposal_scores <= 1)).all()
    # The whole-image box reads every cell of the cropped map and no padding.
    np.testing.assert_allclose(feats[0].box_features[0], feats[0].feature_map.amax(dim=(1, 2)).numpy())
    assert feats[1].box_features.shape == (0, 512)


def test_proposals_are_the_rpn_s_own_boxes_scaled_back(model_dir):
    det = load_detector(model_dir, device="cpu")
    image = torch.rand(3, 240, 320)
    f = detector_features(det, [image])[0]
    with torch.no_grad():
        batch, _ = det.model.transform([image])
        boxes, _ = det.model.rpn(batch, det.model.backbone(batch.tensors))
    sy, sx = f.scale
    np.testing.assert_allclose(f.proposals, boxes[0].numpy() / [sx, sy, sx, sy], rtol=1e-5, atol=1e-3)


def test_region_max_against_brute_force():
    rng = np.random.default_rng(0)
    fmap = torch.from_numpy(rng.normal(size=(5, 6, 9)).astype(np.float32))
    boxes = np.array([[0, 0, 16, 16], [17, 5, 40, 90], [100, 60, 200, 200], [33, 33, 33.5, 33.5]])
    got = region_max(fmap, boxes, 16)
    for (x1, y1, x2, y2), row in zip(boxes, got, strict=True):
        cells = [(r, c) for r in range(6) for c in range(9)
                 if c * 16 < max(x2, x1 + 1e-6) and (c + 1) * 16 > x1
                 and r * 16 < max(y2, y1 + 1e-6) and (r + 1) * 16 > y1]
        cells = cells or [(min(int(y1 // 16), 5), min(int(x1 // 16), 8))]
        np.testing.assert_allclose(row, np.max([fmap[:, r, c].numpy() for r, c in cells], axis=0))


def test_missing_or_mismatched_weights_are_refused(model_dir, tmp_path):
    with pytest.raises(InputError, match="not a trained detector"):
        load_detector(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"builder": {**ARGS, "backbone": "efficientnet_lite0"},
                                                      "classes": []}))
    (tmp_path / "weights.safetensors").write_bytes((model_dir / "weights.safetensors").read_bytes())
    with pytest.raises(InputError, match="does not fit"):
        load_detector(tmp_path)
