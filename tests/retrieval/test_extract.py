"""extract / build-index / evaluate-retrieval / query on a micro reference site with a barely trained detector."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from pipeline.config import load_config
from pipeline.errors import SitelocError
from pipeline.io import tables
from pipeline.sitegen.render import egl_available
from tests.conftest import MICRO_SETS

pytestmark = pytest.mark.skipif(not egl_available(), reason="no headless EGL context for the reference site")

SETS = MICRO_SETS


@pytest.fixture(scope="module")
def site(micro_site):
    return micro_site


@pytest.fixture(scope="module")
def extracted(micro_extraction):
    return micro_extraction


@pytest.fixture(scope="module")
def torch_extracted(site, tmp_path_factory):
    """The micro site extracted by eager torch (the default on a CPU is the exported ONNX graph)."""
    from pipeline.retrieval.extract import run_extract

    _, ing, model = site
    cfg = load_config("ci", [*SETS, "retrieval.engine=torch"])
    return run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path_factory.mktemp("t") / "d"},
                       progress=False)


def test_tables_hold_unit_descriptors_for_every_image(site, extracted):
    _, ing, _ = site
    cat = tables.read_table(extracted / "catalog.parquet", "catalog").to_pydict()
    ipa = tables.read_table(extracted / "ipa.parquet", "ipa")
    rpa = tables.read_table(extracted / "rpa.parquet", "rpa")
    images = tables.read_table(ing / "images.parquet", "images").num_rows
    assert len(cat["image_id"]) > images  # the stops and the query runs' frames
    assert not any(s.startswith("run:mapping") for s in cat["split"])  # a mapping run's frames are never used
    assert any(s.startswith("run:query") for s in cat["split"])
    assert ipa.column("image_id").to_pylist() == cat["image_id"]
    assert ipa.schema.field("descriptor").type.list_size == 112
    np.testing.assert_allclose(np.linalg.norm(tables.descriptor_matrix(ipa), axis=1), 1, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(tables.descriptor_matrix(rpa), axis=1), 1, rtol=1e-4)
    sources = set(rpa.column("source").to_pylist())
    assert "proposal" in sources and sources <= {"proposal", "detection"}
    per_image = np.bincount([cat["image_id"].index(i) for i in rpa.column("image_id").to_pylist()])
    assert per_image.min() >= 1


def test_ipa_is_the_l2_normalised_sum_of_the_cropped_map_and_ignores_padding(site):
    from pipeline.detection.inference import detector_features, load_detector
    from pipeline.retrieval.extract import describe

    _, _, model = site
    det = load_detector(model, device="cpu")
    torch.manual_seed(0)
    small, big = torch.rand(3, 72, 96), torch.rand(3, 150, 130)
    alone = describe(det, [small], 20, 0.3)[0]
    padded = describe(det, [small, big], 20, 0.3)[0]  # batched with a larger image: padded to its size
    np.testing.assert_allclose(padded.ipa, alone.ipa, rtol=1e-4, atol=1e-6)
    fmap = detector_features(det, [small])[0].feature_map.numpy()
    want = fmap.sum(axis=(1, 2))
    np.testing.assert_allclose(alone.ipa, want / np.linalg.norm(want), rtol=1e-5, atol=1e-7)
    order = alone.query_rows(5)
    kinds = [alone.meta[i][0] for i in order]
    assert kinds == sorted(kinds, key=lambda k: k != "detection")


def test_the_onnx_graph_describes_the_site_as_torch_does(extracted, torch_extracted):
    from pipeline.detection.onnx_export import TOLERANCE, _match_regions

    report = json.loads((extracted / "report.json").read_text())
    assert report["engine"] == "onnx" and json.loads((torch_extracted / "report.json").read_text())["engine"] == "torch"
    (graph,) = report["onnx"]["graphs"].values()  # one camera size on the micro site
    assert graph["parity"]["images"] >= 1 and graph["parity"]["max_differences"]["regions_matched"] >= 0.98
    a_ipa, b_ipa = (tables.read_table(d / "ipa.parquet", "ipa") for d in (extracted, torch_extracted))
    assert a_ipa.column("image_id").to_pylist() == b_ipa.column("image_id").to_pylist()
    np.testing.assert_allclose(tables.descriptor_matrix(a_ipa), tables.descriptor_matrix(b_ipa), atol=1e-4)
    tables_rpa = [tables.read_table(d / "rpa.parquet", "rpa") for d in (extracted, torch_extracted)]
    a, b = (t.to_pydict() for t in tables_rpa)
    da, db = (tables.descriptor_matrix(t) for t in tables_rpa)
    matched = total = 0
    for image in a_ipa.column("image_id").to_pylist():  # per image: the same regions, up to ties in score
        ia = [i for i, v in enumerate(a["image_id"]) if v == image]
        ib = [i for i, v in enumerate(b["image_id"]) if v == image]
        boxes = [np.array([[d[k][i] for k in ("x1", "y1", "x2", "y2")] for i in idx]) for d, idx in ((a, ia), (b, ib))]
        pairs = _match_regions(boxes[1], boxes[0], TOLERANCE["box_px"])
        matched, total = matched + len(pairs), total + len(ib)
        for j, i in pairs:
            np.testing.assert_allclose(da[ia[i]], db[ib[j]], atol=1e-3)
    assert matched >= 0.98 * total


def test_interrupted_extraction_resumes_and_a_changed_one_is_refused(site, torch_extracted, tmp_path, monkeypatch):
    import pipeline.retrieval.extract as X

    _, ing, model = site
    cfg = load_config("ci", [*SETS, "retrieval.engine=torch"])  # batches of 4 through X.describe
    real, calls = X.describe, {"n": 0}

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] > 5:  # 4 images per batch, 16 per chunk: dies in the second chunk
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(X, "describe", failing)
    with pytest.raises(KeyboardInterrupt):
        X.run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path / "d"}, progress=False)
    assert (tmp_path / "d.partial" / "ipa-00000.parquet").is_file() and not (tmp_path / "d").exists()
    for change in ("retrieval.rpa_proposals=7", "retrieval.engine=onnx"):
        other = load_config("ci", [*SETS, change])
        with pytest.raises(SitelocError, match="interrupted extraction with another"):
            X.run_extract(other, inputs={"model": model, "data": ing}, outputs={"out": tmp_path / "d"}, progress=False)
    monkeypatch.setattr(X, "describe", real)
    out = X.run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path / "d"}, progress=False)
    assert not (tmp_path / "d.partial").exists()
    for name in ("ipa.parquet", "rpa.parquet", "catalog.parquet"):
        a = tables.read_table(out / name, name.split(".")[0])
        b = tables.read_table(torch_extracted / name, name.split(".")[0])
        assert a.drop_columns(["descriptor"]).equals(b.drop_columns(["descriptor"])) if "descriptor" in \
            a.column_names else a.equals(b)
        if "descriptor" in a.column_names:
            np.testing.assert_allclose(tables.descriptor_matrix(a), tables.descriptor_matrix(b), atol=1e-5)


def _same_tables(out, reference) -> None:
    for name in ("ipa.parquet", "rpa.parquet", "catalog.parquet"):
        a = tables.read_table(out / name, name.split(".")[0])
        b = tables.read_table(reference / name, name.split(".")[0])
        if "descriptor" in a.column_names:
            assert a.drop_columns(["descriptor"]).equals(b.drop_columns(["descriptor"])), name
            np.testing.assert_allclose(tables.descriptor_matrix(a), tables.descriptor_matrix(b), atol=1e-5)
        else:
            assert a.equals(b), name


@pytest.mark.slow
def test_a_damaged_resume_chunk_is_computed_again_and_force_starts_clean(site, torch_extracted, tmp_path,
                                                                        monkeypatch):
    """A corrupted chunk in the resume folder made every rerun fail, --force included."""
    import pipeline.retrieval.extract as X
    from tests.fixtures.log_capture import Warnings

    _, ing, model = site
    cfg = load_config("ci", [*SETS, "retrieval.engine=torch"])
    real, calls = X.describe, {"n": 0}

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] > 5:  # dies in the second chunk, as above
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(X, "describe", failing)
    args = {"inputs": {"model": model, "data": ing}, "outputs": {"out": tmp_path / "d"}, "progress": False}
    with pytest.raises(KeyboardInterrupt):
        X.run_extract(cfg, **args)
    monkeypatch.setattr(X, "describe", real)
    partial = tmp_path / "d.partial"
    ipa0 = partial / "ipa-00000.parquet"
    ipa0.write_bytes(ipa0.read_bytes()[: ipa0.stat().st_size // 2])  # truncated
    with Warnings("pipeline.chunked_encoding") as warned:
        out = X.run_extract(cfg, **args)
    assert f"{ipa0}: damaged resume chunk" in warned.text and "computed again" in warned.text
    assert not partial.exists()
    _same_tables(out, torch_extracted)

    # --force with a resume folder of garbage: another run's plan, unreadable chunks, a stray folder.
    partial.mkdir()
    (partial / "plan.json").write_text('{"fingerprint": "another run"}')
    (partial / "ipa-00000.parquet").write_bytes(b"\x1b[2J garbage" * 50)
    (partial / "rpa-00000.parquet").write_bytes(b"")
    (partial / "stray").mkdir()
    shutil.rmtree(out)
    with pytest.raises(SitelocError, match="another model, site or settings is there.*--force"):
        X.run_extract(cfg, **args)
    assert (partial / "stray").is_dir()  # refused without --force: nothing touched
    out = X.run_extract(cfg, **args, force=True)
    assert not partial.exists()
    _same_tables(out, torch_extracted)


def test_cli_builds_the_index_evaluates_and_answers_a_query(site, extracted, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    cfg, ing, model = site
    runner = CliRunner()
    sets = [a for s in SETS for a in ("--set", s)]
    res = runner.invoke(app, ["build-index", str(extracted), "--out", str(tmp_path / "idx"), "-c", "ci", *sets])
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "idx" / "report.json").read_text())
    assert report["whitening"] == "shrinkage" and report["ipa_dim"] <= 112
    res = runner.invoke(app, ["evaluate-retrieval", str(extracted), str(ing), "--out", str(tmp_path / "ev"), "-c",
                              "ci", *sets])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert set(m["variants"]) | {f"{s} / {w}" for w in m["skipped"] for s in ("ipa", "ipa+rpa")} == {
        f"{s} / {w}" for s in ("ipa", "ipa+rpa") for w in ("none", "pca", "shrinkage", "learned")}
    assert "ipa+rpa / shrinkage" in m["variants"]
    sources = m["by_source"]["sources"]
    assert m["by_source"]["variant"] == "ipa+rpa / shrinkage" and set(sources) <= {"test stops", "run frames"}
    assert sum(t["queries"] for t in sources.values()) == m["query_images"]
    for v in m["variants"].values():
        for key, t in v.items():
            if key not in ("dims", "top1") and t["queries_with_positive"]:
                assert 0 <= t["recall_at_1"] <= t["recall_at_4"] <= t["recall_at_10"] <= 1
        assert 0 <= v["top1"]["beyond_10m"] <= 1 and v["top1"]["median_m"] >= 0
    assert (tmp_path / "ev" / "recall.png").is_file() and (tmp_path / "ev" / "examples.png").is_file()
    from tests.tracked_files import approx, read_headline, read_plot

    main = {s: m["variants"][f"{v} / shrinkage"]["2m_30deg"] for s, v in (("ipa", "ipa"), ("ipa_rpa", "ipa+rpa"))}
    assert read_headline(tmp_path / "ev") == {s: {"map_at_4": approx(t["map_at_4"]),
                                                  "recall_at_1": approx(t["recall_at_1"])} for s, t in main.items()}
    curve = read_plot(tmp_path / "ev", "recall_at_n", ["n", "ipa", "ipa_rpa"])
    assert [r["n"] for r in curve] == [1, 4, 10, 50]
    for r in curve:
        n = int(r["n"])
        assert (r["ipa"], r["ipa_rpa"]) == (approx(main["ipa"][f"recall_at_{n}"]),
                                            approx(main["ipa_rpa"][f"recall_at_{n}"]))
    query_image = ing / tables.read_table(ing / "images.parquet", "images").column("image_id")[0].as_py()
    res = runner.invoke(app, ["query", str(tmp_path / "idx"), str(query_image), "--model", str(model), "--out",
                              str(tmp_path / "q.json"), "-c", "ci", *sets])
    assert res.exit_code == 0, res.output
    answer = json.loads((tmp_path / "q.json").read_text())[str(query_image)]
    assert [round(a["weight"], 3) for a in answer] == [0.4, 0.3, 0.2, 0.1]
    res = runner.invoke(app, ["query", str(tmp_path / "idx"), str(tmp_path / "none.jpg"), "--model", str(model)])
    assert res.exit_code == 1 and "no such file" in res.output


def test_queries_from_another_extraction_use_the_same_database(site, extracted, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    _, ing, _ = site
    runner = CliRunner()
    sets = [a for s in SETS for a in ("--set", s)]
    base = ["evaluate-retrieval", str(extracted), str(ing), "-c", "ci", *sets]
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "a")]).exit_code == 0
    # The same extraction passed as "another" one must give the same figures: queries are picked alike.
    res = runner.invoke(app, [*base, "--out", str(tmp_path / "b"), "--queries", str(extracted), "--queries-data",
                              str(ing)])
    assert res.exit_code == 0, res.output
    a = json.loads((tmp_path / "a" / "metrics.json").read_text())
    b = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert a["variants"] == b["variants"] and b["queries_from"] == str(extracted)
    res = runner.invoke(app, [*base, "--out", str(tmp_path / "c"), "--queries", str(extracted)])
    assert res.exit_code == 1 and "--queries-data" in res.output
