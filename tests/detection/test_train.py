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
    out = run_train_detector(cfg, inputs={"data": site}, outputs={"out": tmp_path / "det"}, progress=False)
    assert len(json.loads((out / "metrics.json").read_text())["loss_history"]) == 12


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
