"""Frame features, windows, places and the sequence LSTM's training on the micro reference site."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.errors import SitelocError
from pipeline.sequence.model import place_labels, windows
from pipeline.sequence.train import recall_within
from tests.conftest import SEQUENCE_SETS as FAST


def test_windows_stay_inside_a_segment_and_skip_gaps():
    steps = np.array([0, 1, 2, 3, 5, 6, 7, 8])  # step 4 has no frame
    breaks = np.array([0, 0, 0, 0, 0, 0, 1, 0], bool)  # a kidnapping before step 7
    np.testing.assert_array_equal(windows(steps, breaks, 3), [[0, 1, 2], [1, 2, 3]])
    np.testing.assert_array_equal(windows(steps, np.zeros(8, bool), 2), [[0, 1], [1, 2], [2, 3], [4, 5], [5, 6],
                                                                         [6, 7]])
    assert windows(steps, breaks, 5).shape == (0, 5)


def test_place_labels_bin_cells_and_headings():
    xy = np.array([[0.5, 0.5], [1.9, 0.1], [2.1, 0.0], [0.5, 0.5]])
    theta = np.array([0.1, -0.1 + 2 * math.pi, 0.0, math.pi])
    labels, places = place_labels(xy, theta, 2.0, 4)
    assert places == [(0, 0, 0), (0, 0, 2), (0, 0, 3), (1, 0, 0)]
    np.testing.assert_array_equal(labels, [0, 2, 3, 1])


def test_recall_within_counts_any_of_the_found():
    found = np.array([[[0.0, 0.0], [5.0, 5.0]], [[9.0, 9.0], [8.0, 8.0]]])
    assert recall_within(found, np.array([[5.5, 5.0], [0.0, 0.0]]), 1.0) == 0.5


def test_recalls_over_the_reachable_queries():
    from pipeline.sequence.train import _recalls

    db = np.array([[0.0, 0.0], [10.0, 0.0]])
    queries = np.array([[0.5, 0.0], [10.5, 0.0], [50.0, 0.0]])  # the third has nothing within 2 m
    found = db[np.array([[1, 0], [1, 0], [0, 1]])]  # first: right only at rank 2; second: right at rank 1
    r = _recalls(found, queries, db)
    assert r["reachable_2m"] == pytest.approx(2 / 3)
    assert r["recall_at_1_2m"] == pytest.approx(1 / 3) and r["recall_at_4_2m"] == pytest.approx(2 / 3)
    assert r["recall_at_1_reachable_2m"] == 0.5 and r["recall_at_4_reachable_2m"] == 1.0


@pytest.fixture(scope="module")
def frames(micro_frames):
    return micro_frames


def test_frame_features_are_the_classifiers_logits_of_every_run_frame(frames):
    import torch

    from pipeline.detection.inference import load_image
    from pipeline.io import tables
    from pipeline.sequence.frames import FrameEncoder

    cfg, ing, out = frames
    t = tables.read_table(out / "frames.parquet", "frames")
    runs = {p.stem: tables.read_table(p, "runs").num_rows for p in (ing / "runs").glob("*.parquet")}
    assert t.num_rows == sum(runs.values()) and set(t.column("run").to_pylist()) == set(runs)
    assert t.schema.field("descriptor").type.list_size == 1000
    enc = FrameEncoder("imagenet", cfg.sequence.frame_size)
    k = t.num_rows // 2
    image = load_image(ing / t.column("image_id")[k].as_py())
    assert min(enc.prepare(image).shape[-2:]) == cfg.sequence.frame_size
    with torch.no_grad():  # the same image through the classifier by hand
        x = (enc.prepare(image)[None] - 0.5) / 0.5
        ref = enc.model(x).numpy()[0]
    np.testing.assert_allclose(tables.descriptor_matrix(t)[k], ref, rtol=1e-4, atol=1e-4)
    report = json.loads((out / "report.json").read_text())  # on a CPU the logits come from the bundle's graph
    assert report["engine"] == "onnx"
    assert [g["max_abs"] <= g["tolerance"] for g in report["onnx"]["graphs"].values()] == [True]


def test_frame_features_by_torch_match_the_onnx_ones(frames, tmp_path):
    from pipeline.config import load_config
    from pipeline.io import tables
    from pipeline.sequence.frames import run_frame_features
    from tests.conftest import MICRO_SETS, SEQUENCE_SETS

    _, ing, out = frames
    cfg = load_config("ci", [*MICRO_SETS, *SEQUENCE_SETS, "sequence.engine=torch"])
    ref = run_frame_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "f"}, progress=False)
    a, b = (tables.read_table(d / "frames.parquet", "frames") for d in (out, ref))
    assert a.drop_columns(["descriptor"]).equals(b.drop_columns(["descriptor"]))
    # Logits up to about 20: 1.05e-4 apart at most on an AMD EPYC (AVX2), well within the 5e-3 the export
    # refuses beyond (`onnx_export.export_frame_encoder`).
    np.testing.assert_allclose(tables.descriptor_matrix(a), tables.descriptor_matrix(b), atol=1e-4, rtol=1e-5)
    assert json.loads((ref / "report.json").read_text())["engine"] == "torch"


def test_training_builds_a_whitened_database_and_resumes(frames, tmp_path, monkeypatch):
    import torch

    import pipeline.sequence.train as T
    from pipeline.config import load_config
    from pipeline.io import tables
    from pipeline.retrieval.whitening import PCAWhitening
    from tests.conftest import MICRO_SETS

    cfg, ing, fr = frames
    out = T.run_train_sequence(cfg, inputs={"frames": fr, "data": ing}, outputs={"out": tmp_path / "s"}, progress=False)
    m = json.loads((out / "metrics.json").read_text())
    f = T.Frames(fr / "frames.parquet")
    mapping = sorted(r for r in set(f.run) if r.startswith("mapping"))
    assert m["train_windows"] == len(f.windows(mapping, 3)) and len(m["loss_history"]) == 4
    assert m["loss_history"][-1] < m["loss_history"][0]
    db = tables.read_table(out / "database.parquet", "sequences")
    assert db.num_rows == m["train_windows"]
    d = tables.descriptor_matrix(db)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, rtol=1e-5)
    w = PCAWhitening.load(out / "whitening.npz")
    assert w.n_components_ == m["dims"] == d.shape[1]
    assert {"length_1", "length_3", "single_frame"} <= set(m["recall"])
    from tests.tracked_files import approx, read_headline, read_plot

    assert read_headline(out) == {  # sequence.length=3 here (the paper's 6: recall_at_1_2m_6_frames)
        "recall_at_1_2m_3_frames": approx(m["recall"]["length_3"]["recall_at_1_2m"]),
        "recall_at_1_2m_single_frame": approx(m["recall"]["single_frame"]["recall_at_1_2m"])}
    loss = read_plot(out, "loss", ["epoch", "loss"])
    assert [r["epoch"] for r in loss] == [1, 2, 3, 4] and [r["loss"] for r in loss] == [approx(v) for v in
                                                                                      m["loss_history"]]

    # An interruption after 2 epochs resumes there: only the 2 remaining epochs run again.
    calls = []
    real = torch.nn.functional.cross_entropy

    def interrupt(*a, **k):
        calls.append(1)
        if len(calls) == 2 * math.ceil(m["train_windows"] / 75) + 1:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(torch.nn.functional, "cross_entropy", interrupt)
    with pytest.raises(KeyboardInterrupt):
        T.run_train_sequence(cfg, inputs={"frames": fr}, outputs={"out": tmp_path / "r"}, progress=False)
    assert torch.load(tmp_path / "r.partial" / "checkpoint.pt", weights_only=True)["epoch"] == 2
    calls.clear()
    monkeypatch.setattr(torch.nn.functional, "cross_entropy", lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    other = load_config("ci", [*MICRO_SETS, *FAST, "sequence.lr=0.01"])
    with pytest.raises(SitelocError, match="another training"):
        T.run_train_sequence(other, inputs={"frames": fr}, outputs={"out": tmp_path / "r"}, progress=False)
    again = T.run_train_sequence(cfg, inputs={"frames": fr}, outputs={"out": tmp_path / "r"}, progress=False)
    assert len(calls) == 2 * math.ceil(m["train_windows"] / 75)
    assert json.loads((again / "metrics.json").read_text())["loss_history"] == m["loss_history"]  # same seeds


def test_cli_trains_and_refuses_a_site_without_frames(frames, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    cfg, ing, fr = frames
    sets = [a for s in FAST for a in ("--set", s)]
    res = CliRunner().invoke(app, ["train-sequence", str(fr), "--out", str(tmp_path / "s"), "--config", "ci", *sets])
    assert res.exit_code == 0, res.output
    assert "recall@1" in res.output and (tmp_path / "s" / "weights.safetensors").is_file()
    empty = tmp_path / "empty"
    (empty / "runs").mkdir(parents=True)
    res = CliRunner().invoke(app, ["frame-features", str(empty), "--out", str(tmp_path / "x"), "--config", "ci"])
    assert res.exit_code == 1 and "no run has camera frames" in res.output and "Traceback" not in res.output


def test_keep_model_describes_new_frames_with_the_trained_lstm(frames, tmp_path):
    """The database of frames changed in one stretch of a mapping run: windows that do not touch the
    stretch keep the trained database's descriptors, those that do differ; nothing is trained."""
    import pyarrow.parquet as pq
    from typer.testing import CliRunner

    import pipeline.sequence.train as T
    from pipeline.io import tables
    from pipeline.sequence.database import run_sequence_database
    from stages.app import app

    cfg, ing, fr = frames
    trained = T.run_train_sequence(cfg, inputs={"frames": fr}, outputs={"out": tmp_path / "s"}, progress=False)
    t = pq.read_table(fr / "frames.parquet")
    f = T.Frames(fr / "frames.parquet")
    run = sorted(r for r in set(f.run) if r.startswith("mapping"))[0]
    steps = sorted(int(s) for s, r in zip(t.column("step").to_pylist(), t.column("run").to_pylist(), strict=True)
                   if r == run)
    changed_steps = set(steps[len(steps) // 2: len(steps) // 2 + 4])
    rows = [i for i, (s, r) in enumerate(zip(t.column("step").to_pylist(), t.column("run").to_pylist(), strict=True))
            if r == run and int(s) in changed_steps]
    d = tables.descriptor_matrix(t).copy()
    d[rows] = np.random.default_rng(0).standard_normal((len(rows), d.shape[1])).astype(np.float32)
    (tmp_path / "f2").mkdir()
    pq.write_table(t.set_column(t.column_names.index("descriptor"), "descriptor", tables.descriptor_array(d)),
                   tmp_path / "f2" / "frames.parquet")
    out = run_sequence_database(cfg, inputs={"frames": tmp_path / "f2", "model": trained},
                                outputs={"out": tmp_path / "db"})
    old = tables.read_table(trained / "database.parquet", "sequences")
    new = tables.read_table(out / "database.parquet", "sequences")
    assert new.column("end_step").to_pylist() == old.column("end_step").to_pylist()
    a, b = tables.descriptor_matrix(old), tables.descriptor_matrix(new)
    length = int(json.loads((trained / "config.json").read_text())["length"])
    ends, runs = new.column("end_step").to_pylist(), new.column("run").to_pylist()
    touched = np.array([r == run and any(e - k in changed_steps for k in range(length))
                        for r, e in zip(runs, ends, strict=True)])
    assert 0 < touched.sum() < len(touched)
    np.testing.assert_allclose(b[~touched], a[~touched], atol=1e-5)
    assert np.all(np.abs(b[touched] - a[touched]).max(axis=1) > 1e-3)
    for name in ("weights.safetensors", "whitening.npz"):
        assert (out / name).read_bytes() == (trained / name).read_bytes()
    m = json.loads((out / "metrics.json").read_text())
    assert m["epochs"] == 0 and m["kept_model"] == str(trained) and "length_3" in m["recall"]
    # From the CLI: a directory that is not a sequence model is refused, nothing written
    res = CliRunner().invoke(app, ["train-sequence", str(fr), "--keep-model", str(fr), "--out", str(tmp_path / "x"),
                                   "--config", "ci", *[a for s in FAST for a in ("--set", s)]])
    assert res.exit_code == 1 and "not a `siteloc train-sequence` output" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "x").exists()
