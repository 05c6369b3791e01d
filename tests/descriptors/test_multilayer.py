"""Multi-layer CNN features (seed 001): layer shapes, the ONNX-friendly pooling, weights by file."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pipeline.descriptors.multilayer import BACKBONES, MultiLayerEncoder, build_multilayer, grid_max_pool, layer_names


@pytest.mark.parametrize("shape", [(7, 7), (2, 2), (1, 1), (5, 8), (15, 20)])
def test_grid_max_pool_is_adaptive_max_pool(shape):
    x = torch.randn(2, 4, *shape)
    assert torch.equal(grid_max_pool(x, 3), F.adaptive_max_pool2d(x, 3))


@pytest.mark.parametrize("backbone,size,dims", [("alexnet", 224, (9216, 4096, 4096)),
                                                ("vgg16", 64, (25088, 4096, 4096)),
                                                ("efficientnet_lite0", 64, (2880, 1280, 1000))])
def test_layers_have_the_papers_sizes_and_unit_norm(backbone, size, dims):
    enc = MultiLayerEncoder(backbone, None, size)
    feats = enc([torch.rand(3, 48, 64), torch.rand(3, 48, 64)])
    assert tuple(feats) == BACKBONES[backbone]
    assert tuple(v.shape[1] for v in feats.values()) == dims
    for v in feats.values():
        assert v.dtype == np.float32 and v.shape[0] == 2
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)


def test_fc_layers_follow_their_relu_and_pool5_is_the_conv_output():
    model, _ = build_multilayer("alexnet", None)
    x = torch.randn(1, 3, 224, 224)
    with torch.no_grad():
        pool5, fc6, fc7 = model(x)
        ref = torch.flatten(model.avgpool(model.features(x)), 1)
        assert torch.equal(pool5, ref)
        assert torch.equal(fc6, torch.relu(model.linears[0](ref)))
        assert (fc7 >= 0).all()


def test_random_weights_are_the_same_network_every_time():
    x = [torch.rand(3, 40, 50)]
    a = MultiLayerEncoder("efficientnet_lite0", None, 64)(x)
    b = MultiLayerEncoder("efficientnet_lite0", None, 64)(x)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_weights_from_a_file_load_strictly(tmp_path):
    from torchvision.models import alexnet

    net = alexnet(weights=None)
    torch.save(net.state_dict(), tmp_path / "alexnet.pth")
    model, source = build_multilayer("alexnet", tmp_path / "alexnet.pth")
    assert source == f"file: {tmp_path / 'alexnet.pth'}"
    assert torch.equal(model.features[0].weight, net.features[0].weight)
    torch.save({"bogus": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(RuntimeError):
        build_multilayer("alexnet", tmp_path / "bad.pth")


def test_unknown_backbone_is_named():
    with pytest.raises(ValueError, match="one of alexnet, vgg16, efficientnet_lite0"):
        layer_names("resnet50")


def test_missing_weights_are_a_clear_error(tmp_path):
    from pipeline.errors import InputError

    with pytest.raises(InputError, match="weights file not found"):
        build_multilayer("efficientnet_lite0", tmp_path / "nope.pth")
