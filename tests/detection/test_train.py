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
    res = runner.invoke(app, ["train-detector", str(tmp_path), "--out", str(tmp_path / "n"), "--config", "ci"])
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
