"""train-detector on a micro reference site: the loss falls, checkpoints resume and refuse pickles."""

from __future__ import annotations

import json
import pickle

import pytest
import torch

from pipeline.config import load_config
from pipeline.detection.train import TrainingError, run_train_detector
from pipeline.ingest import run_ingest
from pipeline.sitegen.render import egl_available
from tests.tracked_files import approx, read_headline, read_plot

pytestmark = pytest.mark.skipif(not egl_available(), reason="no headless EGL context for the reference site")

SMALL = ["detector.weights=null", "detector.max_side=96", "detector.min_size=72", "detector.max_size=96",
         "detector.batch_size=2", "detector.lr=0.005"]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    from pipeline.sitegen.presets import load_site_preset
    from pipeline.sitegen.synth import run_synth

    cfg = load_config("ci")
    root = tmp_path_factory.mktemp("train")
    preset = load_site_preset(cfg.synth.site, cfg.synth.preset_overrides)
    synth = run_synth(preset, outputs={"out": root / "site"}, seed=cfg.synth.seed, progress=False)
    return run_ingest(cfg, inputs={"site": synth}, outputs={"out": root / "ing"}, progress=False)


def test_training_lowers_the_loss_and_writes_safetensors(site, tmp_path):
    cfg = load_config("ci", [*SMALL, "detector.iterations=30", "detector.checkpoint_every=10"])
    out = run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    m = json.loads((out / "metrics.json").read_text())
    hist = m["loss_history"]
    assert len(hist) == 30 and sum(hist[-10:]) < sum(hist[:10])
    assert read_headline(out) == {"loss_first": approx(hist[0]), "loss_last_50_mean": approx(sum(hist) / 30),
                                  "val_loss": approx(m["val_loss"])}
    curve = read_plot(out, "loss", ["iteration", "loss"])
    assert [r["iteration"] for r in curve] == list(range(30))  # 0-based, as the training loop counts
    assert [r["loss"] for r in curve] == [approx(v) for v in hist]
    c = json.loads((out / "config.json").read_text())
    assert c["builder"]["num_classes"] == 9 and c["weights_source"].startswith("none")
    from safetensors.torch import load_file

    state = load_file(str(out / "weights.safetensors"))
    assert any(k.startswith("roi_heads.box_predictor") for k in state)
    assert not (tmp_path / "det.partial").exists()


def test_interrupted_training_resumes_from_its_checkpoint(site, tmp_path, monkeypatch):
    import pipeline.detection.train as T

    cfg = load_config("ci", [*SMALL, "detector.iterations=12", "detector.checkpoint_every=5"])
    calls = {"n": 0}
    real = T._loss

    def failing(model, images, targets):
        calls["n"] += 1
        if calls["n"] == 8:
            raise KeyboardInterrupt
        return real(model, images, targets)

    monkeypatch.setattr(T, "_loss", failing)
    with pytest.raises(KeyboardInterrupt):
        run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    ckpt = tmp_path / "det.partial" / "checkpoint.pt"
    assert ckpt.is_file() and not (tmp_path / "det").exists()
    assert torch.load(ckpt, weights_only=True)["iteration"] == 5
    monkeypatch.setattr(T, "_loss", real)
    other = load_config("ci", [*SMALL, "detector.iterations=12", "detector.checkpoint_every=5", "detector.lr=0.001"])
    with pytest.raises(TrainingError, match="a checkpoint of another training"):  # never continued silently
        run_train_detector(other, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    assert ckpt.is_file()
    resumed = []
    monkeypatch.setattr(T, "_loss", lambda *a: (resumed.append(1), real(*a))[1])
    out = run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    hist = json.loads((out / "metrics.json").read_text())["loss_history"]
    assert len(hist) == 12 and len(read_plot(out, "loss", ["iteration", "loss"])) == 12  # the resumed part too
    assert read_headline(out)["loss_first"] == approx(hist[0])
    # --force: another training's checkpoint is discarded and training starts afresh
    monkeypatch.setattr(T, "_loss", failing)
    calls["n"] = 0
    with pytest.raises(KeyboardInterrupt):
        run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det3"}, progress=False)
    steps = []
    monkeypatch.setattr(T, "_loss", lambda *a: (steps.append(1), real(*a))[1])
    run_train_detector(other, inputs={"data": site}, outputs={"out": tmp_path / "det3"}, force=True, progress=False)
    assert len(steps) - len(resumed) == 5  # iterations 0-4 again (the same validation passes in both)


def test_a_pickled_checkpoint_is_refused_and_a_nan_loss_stops(site, tmp_path, monkeypatch):
    cfg = load_config("ci", [*SMALL, "detector.iterations=3"])
    partial = tmp_path / "det.partial"
    partial.mkdir()
    (partial / "checkpoint.pt").write_bytes(pickle.dumps({"model": print}, protocol=2))
    with pytest.raises(pickle.UnpicklingError):
        run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    import pipeline.detection.train as T

    monkeypatch.setattr(T, "_loss", lambda *a: (torch.tensor(float("nan"), requires_grad=True), {"loss": float("nan")}))
    with pytest.raises(TrainingError, match="non-finite loss at iteration 0"):
        run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det2"}, progress=False)


def test_cli_trains_and_refuses_what_is_not_a_site(site, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    runner = CliRunner()
    args = ["train-detector", str(site), "--out", str(tmp_path / "m"), "--config", "ci"]
    for item in [*SMALL, "detector.iterations=4"]:
        args += ["--set", item]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "trained efficientnet_lite0 (none (random init))" in res.output
    assert (tmp_path / "m" / "weights.safetensors").is_file()
    (tmp_path / "not-a-site").mkdir()
    res = runner.invoke(app, ["train-detector", str(tmp_path / "not-a-site"), "--out", str(tmp_path / "n"),
                              "--config", "ci"])
    assert res.exit_code == 1 and "images.parquet" in res.output and "Traceback" not in res.output


def test_evaluate_cli_scores_held_out_stops_and_draws_them(site, tmp_path):
    from PIL import Image
    from typer.testing import CliRunner

    from stages.app import app

    runner = CliRunner()
    sets = [a for item in [*SMALL, "detector.iterations=6"] for a in ("--set", item)]
    trained = runner.invoke(app, ["train-detector", str(site), "--out", str(tmp_path / "m"), "-c", "ci", *sets])
    assert trained.exit_code == 0, trained.output
    res = runner.invoke(app, ["evaluate-detector", str(tmp_path / "m"), str(site), "--out", str(tmp_path / "e"),
                              "-c", "ci", *sets])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "e" / "metrics.json").read_text())
    test_stops = {r for r, s in zip(*_stops_and_splits(site), strict=True) if s == "test"}
    assert m["split"] == "test" and m["stops"] == len(test_stops)
    assert set(m["per_class"]) == set(json.loads((tmp_path / "m" / "config.json").read_text())["classes"])
    assert sum(v["gt"] for v in m["per_class"].values()) > 0
    assert m["map_50"] is None or 0.0 <= m["map_50"] <= 1.0
    assert read_headline(tmp_path / "e") == {"map_50": approx(m["map_50"]), "map_50_95": approx(m["map_50_95"])}
    ap = read_plot(tmp_path / "e", "ap_per_class", ["class", "ap_50", "ap_50_95"])
    assert [r["class"] for r in ap] == json.loads((tmp_path / "m" / "config.json").read_text())["classes"]
    for r in ap:  # an empty cell where metrics.json has null (a class without ground truth)
        v = m["per_class"][r["class"]]
        assert (r["ap_50"], r["ap_50_95"]) == (approx(v["ap_50"]), approx(v["ap_50_95"]))
    assert "mAP@0.5" in res.output
    assert Image.open(tmp_path / "e" / "predictions.png").size[0] > 400
    json.loads((tmp_path / "e" / "detections.json").read_text())
    # A split that does not exist is a clear error, not a crash.
    res = runner.invoke(app, ["evaluate-detector", str(tmp_path / "m"), str(site), "--out", str(tmp_path / "f"),
                              "-c", "ci", "--set", "detector.eval_split=query"])
    assert res.exit_code == 1 and "no 'query' images" in res.output and "Traceback" not in res.output


def _stops_and_splits(site):
    from pipeline.io import tables

    t = tables.read_table(site / "images.parquet", "images").to_pydict()
    return t["stop_id"], t["split"]


def test_learning_rate_warms_up_then_drops_tenfold():
    from pipeline.detection.train import learning_rate

    d = load_config("ci", ["detector.lr=0.01", "detector.iterations=100", "detector.warmup_iterations=10",
                           "detector.lr_drop_at=0.7"]).detector
    assert learning_rate(0, d) == pytest.approx(1e-4)
    assert learning_rate(5, d) == pytest.approx(0.01 * (0.01 + 0.99 * 0.5))
    assert learning_rate(10, d) == learning_rate(69, d) == pytest.approx(0.01)
    assert learning_rate(70, d) == learning_rate(99, d) == pytest.approx(0.001)


def test_paper_recipe_gives_biases_twice_the_lr_and_no_decay():
    from pipeline.detection.builders import build_detector
    from pipeline.detection.train import param_groups

    d = load_config("paper").detector
    assert (d.backbone, d.min_size, d.max_size, tuple(d.anchor_sizes), d.rpn_post_nms_top_n_test) == (
        "vgg16", 600, 1000, (128, 256, 512), 300)
    model = build_detector(backbone="vgg16", num_classes=9, weights=None, min_size=64, max_size=64).model
    weights, biases = param_groups(model, d)
    assert biases["lr_factor"] == 2.0 and biases["weight_decay"] == 0.0 and weights["lr_factor"] == 1.0
    trainable = {id(p) for p in model.parameters() if p.requires_grad}
    grouped = [id(p) for p in weights["params"] + biases["params"]]
    assert len(grouped) == len(set(grouped)) and set(grouped) == trainable
    assert all(p.ndim == 1 for p in biases["params"])


# --init-from: fine-tuning an earlier train-detector output (issue 26, after `siteloc update`).
# The earlier model is trained from the ImageNet weights, so its batch norms are frozen (as the configured weights
# decide) and every tensor of the state dict, statistics included, can only change through the optimizer.
INIT = [*SMALL, "detector.weights=imagenet", "detector.iterations=2"]


@pytest.fixture(scope="module")
def old_model(site, tmp_path_factory):
    out = tmp_path_factory.mktemp("init") / "old"
    return run_train_detector(load_config("ci", INIT), inputs={"data": site}, outputs={"out": out}, progress=False)


@pytest.fixture(scope="module")
def fine_tuned(site, old_model, tmp_path_factory):
    """Two iterations from `old_model` with the schedule's learning rate forced to 0 (the config insists on
    lr > 0 and iterations >= 1): forward, backward and optimizer steps all run, and nothing may move."""
    import pipeline.detection.train as T

    out = tmp_path_factory.mktemp("init") / "new"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(T, "learning_rate", lambda it, d: 0.0)
        run_train_detector(load_config("ci", INIT), inputs={"data": site, "init_from": old_model},
                           outputs={"out": out}, progress=False)
    return out


def test_init_from_starts_from_the_old_models_weights(old_model, fine_tuned):
    from safetensors.torch import load_file

    from pipeline.detection.builders import build_detector

    old, new = load_file(str(old_model / "weights.safetensors")), load_file(str(fine_tuned / "weights.safetensors"))
    assert old.keys() == new.keys()
    assert all(torch.equal(old[k], new[k]) for k in old)  # bit for bit: the old weights, not ImageNet's
    assert len(json.loads((fine_tuned / "metrics.json").read_text())["loss_history"]) == 2  # it did train
    # ... and the check is not vacuous: the configured (ImageNet) start is not the old model.
    c = json.loads((old_model / "config.json").read_text())
    torch.manual_seed(0)
    fresh = build_detector(weights="imagenet", **c["builder"]).model.state_dict()
    assert not all(torch.equal(fresh[k], old[k]) for k in old)


def test_init_from_is_recorded_and_separates_checkpoints(old_model, fine_tuned):
    import hashlib
    from types import SimpleNamespace

    import yaml

    from pipeline.detection.train import _fingerprint

    c = json.loads((fine_tuned / "config.json").read_text())
    sha = hashlib.sha256((old_model / "weights.safetensors").read_bytes()).hexdigest()
    assert c["init_from"] == {"path": str(old_model), "weights_sha256": sha}
    assert c["weights_source"].startswith(f"init-from: {old_model}") and sha[:12] in c["weights_source"]
    assert c["builder"] == json.loads((old_model / "config.json").read_text())["builder"]
    assert c["frozen"] == json.loads((old_model / "config.json").read_text())["frozen"]
    assert "init_from" not in json.loads((old_model / "config.json").read_text())
    eff = yaml.safe_load((fine_tuned / "config.yaml").read_text())
    assert eff["inputs"]["init_from"] == str(old_model) and eff["config"]["detector"]["iterations"] == 2
    # A checkpoint of a training from other weights (or from detector.weights) is never resumed.
    d, train = load_config("ci", INIT).detector, [SimpleNamespace(image_id="a")]
    prints = {_fingerprint(d, train), _fingerprint(d, train, c["init_from"]),
              _fingerprint(d, train, {**c["init_from"], "weights_sha256": "0" * 64})}
    assert len(prints) == 3


def _copy_model(src, dst, **changes):
    import shutil

    shutil.copytree(src, dst)
    c = json.loads((dst / "config.json").read_text())
    for key, value in changes.items():
        if key == "classes":
            c["classes"] = value
        else:
            c["builder"][key] = value
    (dst / "config.json").write_text(json.dumps(c))
    return dst


def test_init_from_refuses_another_network_and_writes_nothing(site, old_model, tmp_path):
    from pipeline.errors import InputError

    cfg = load_config("ci", INIT)

    def refused(init, match):
        with pytest.raises(InputError, match=match) as exc:
            run_train_detector(cfg, inputs={"data": site, "init_from": init}, outputs={"out": tmp_path / "det"},
                               progress=False)
        assert not (tmp_path / "det").exists() and not (tmp_path / "det.partial").exists()
        return str(exc.value)

    # other classes
    classes = json.loads((old_model / "config.json").read_text())["classes"]
    msg = refused(_copy_model(old_model, tmp_path / "cls", classes=classes[::-1]), "config.json")
    assert "key 'classes'" in msg and str(classes[::-1]) in msg and str(classes) in msg and "fix:" in msg
    # other builder arguments: both values and the --set that would match the model
    msg = refused(_copy_model(old_model, tmp_path / "arg", anchor_sizes=[8, 16], max_size=128), "config.json")
    assert "key 'builder.anchor_sizes'" in msg and "[8, 16]" in msg and "[16, 32, 64]" in msg
    assert "--set detector.anchor_sizes=[8,16]" in msg and "--set detector.max_size=128" in msg
    # batch norms frozen or not follow detector.weights: a model trained from random weights does not fit
    msg = refused(_copy_model(old_model, tmp_path / "bn", frozen_batch_norm=False), "frozen_batch_norm")
    assert "False" in msg and "True" in msg and "detector.weights" in msg
    # a directory that is not a train-detector output, or none at all
    msg = refused(tmp_path / "nowhere", "not a trained detector")
    assert f"{tmp_path / 'nowhere'}: no such directory" in msg and "point --init-from at" in msg
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "config.json").write_text((old_model / "config.json").read_text())
    assert "weights.safetensors: missing" in refused(tmp_path / "half", "not a trained detector")
    bad = _copy_model(old_model, tmp_path / "bytes")
    (bad / "weights.safetensors").write_bytes(b"\x80\x02not safetensors")  # never unpickled
    assert "weights.safetensors: not a safetensors file" in refused(bad, "unreadable weights")


def test_cli_refuses_a_bad_init_from_without_a_traceback(site, old_model, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    runner = CliRunner()
    sets = [a for item in INIT for a in ("--set", item)]
    res = runner.invoke(app, ["train-detector", str(site), "--out", str(tmp_path / "m"), "-c", "ci", *sets,
                              "--init-from", str(tmp_path / "missing")])
    assert res.exit_code == 1 and "Traceback" not in res.output, res.output
    assert "--init-from" in res.output and "missing: no such directory" in res.output
    other = _copy_model(old_model, tmp_path / "other", backbone="vgg16")
    res = runner.invoke(app, ["train-detector", str(site), "--out", str(tmp_path / "m"), "-c", "ci", *sets,
                              "--init-from", str(other)])
    assert res.exit_code == 1 and "Traceback" not in res.output, res.output
    assert "builder.backbone" in res.output and "'vgg16'" in res.output and "'efficientnet_lite0'" in res.output
    assert not (tmp_path / "m").exists()
