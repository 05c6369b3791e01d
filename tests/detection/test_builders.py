"""Detector builders: the documented layout (stride 16, RoI max pooling, frozen layers) and one working step."""

from __future__ import annotations

import pytest
import torch

from pipeline.detection.builders import RoIMaxPool, build_detector


@pytest.mark.parametrize(("backbone", "channels"), [("vgg16", 512), ("efficientnet_lite0", 112)])
def test_layout_shapes_and_frozen_layers(backbone, channels):
    built = build_detector(backbone=backbone, num_classes=9, weights=None, min_size=160, max_size=224)
    model = built.model.eval()
    assert built.weights_source.startswith("none")
    assert isinstance(model.roi_heads.box_roi_pool, RoIMaxPool)
    assert model.roi_heads.box_predictor.cls_score.out_features == 9
    assert model.roi_heads.box_predictor.bbox_pred.out_features == 9 * 4
    x = torch.rand(1, 3, 160, 208)
    with torch.no_grad():
        feats = model.backbone(x)
    assert list(feats) == ["0"] and feats["0"].shape[:2] == (1, channels)
    assert feats["0"].shape[2:] == (160 // 16, 208 // 16)  # stride 16
    frozen = [n for n, p in model.named_parameters() if not p.requires_grad]
    assert frozen and all(any(n.startswith(f) for f in built.frozen) for n in frozen)
    assert model.rpn.anchor_generator.num_anchors_per_location() == [9]


def test_roi_max_pool_is_max_pooling():
    feat = torch.arange(64, dtype=torch.float32).reshape(1, 1, 8, 8)  # value = 8 * row + col
    # Image box (0, 0)-(63, 63) at 1/16 covers feature cells 0..4 (rounded ends, inclusive); 2 x 2 bins of
    # 2.5 cells span rows/cols [0, 3) and [2, 5): each output is the max of its bin, its bottom-right cell.
    pooled = RoIMaxPool(output_size=2)({"0": feat}, [torch.tensor([[0.0, 0.0, 63.0, 63.0]])])
    assert pooled[0, 0].tolist() == [[18.0, 20.0], [34.0, 36.0]]


@pytest.mark.parametrize("backbone", ["efficientnet_lite0"])
def test_one_training_step_lowers_the_loss_on_a_repeated_batch(backbone):
    torch.manual_seed(0)
    built = build_detector(backbone=backbone, num_classes=9, weights=None, min_size=128, max_size=160,
                           anchor_sizes=(32, 64, 128))
    model = built.model.train()
    images = [torch.rand(3, 120, 160) for _ in range(2)]
    targets = [{"boxes": torch.tensor([[20.0, 30.0, 80.0, 100.0]]), "labels": torch.tensor([3])},
               {"boxes": torch.tensor([[50.0, 10.0, 150.0, 60.0]]), "labels": torch.tensor([5])}]
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.01, momentum=0.9)
    frozen_before = {n: p.detach().clone() for n, p in model.named_parameters() if not p.requires_grad}
    losses = []
    for _ in range(8):
        loss = sum(model(images, targets).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0]
    for n, p in model.named_parameters():
        if n in frozen_before:
            assert torch.equal(p, frozen_before[n]), n


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="backbone"):
        build_detector(backbone="resnet", num_classes=9, weights=None)
    with pytest.raises(ValueError, match="background"):
        build_detector(backbone="vgg16", num_classes=1, weights=None)
