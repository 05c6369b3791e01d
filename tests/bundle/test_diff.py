"""Bundle versions: `export --parent` names its parent and ships a changelog; `siteloc diff` compares bundles."""

from __future__ import annotations

import json
import shutil

import pytest
from typer.testing import CliRunner

from pipeline.bundle.diff import DiffError, diff_bundles, next_version, read_view, stop_fingerprints
from pipeline.bundle.export import run_export
from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.retrieval.database import run_build_index
from pipeline.retrieval.extract import run_extract
from pipeline.runtime.bundle import verify_bundle
from pipeline.update.site_update import run_update
from stages.app import app
from tests.fixtures.recapture import lone_database_stop, mirrored_stop


@pytest.fixture(scope="module")
def bundle_v2(micro_bundle, micro_extraction, tmp_path_factory):
    """(stop, area key, v2 bundle): one database stop re-captured (mirrored), updated, re-extracted with
    --reuse, indexed and exported with the micro bundle as its parent."""
    cfg, ing, model, _, v1 = micro_bundle
    root = tmp_path_factory.mktemp("v2")
    stop, key = lone_database_stop(v1)
    new = mirrored_stop(ing, root / "new", stop)
    site = run_update(cfg, inputs={"site_db": ing, "new_data": new}, outputs={"out": root / "site"}, progress=False)
    x = run_extract(cfg, inputs={"model": model, "data": site, "reuse": micro_extraction},
                    outputs={"out": root / "x"}, progress=False)
    index = run_build_index(cfg, inputs={"descriptors": x}, outputs={"out": root / "index"})
    cfg2 = cfg.model_copy(update={"export": cfg.export.model_copy(update={"version": next_version(
        cfg.export.version)})})
    v2 = run_export(cfg2, inputs={"parent": v1, "model": model, "index": index, "data": site},
                    outputs={"out": root / "bundles"})
    return stop, key, v2


def test_the_next_version_raises_the_last_number():
    assert next_version("0.1.0") == "0.1.1" and next_version("v9") == "v10"
    assert next_version("2.3-rc") == "2.4-rc" and next_version("beta") == "beta.1"


def test_the_new_bundle_names_its_parent_and_its_changelog_lists_exactly_the_recaptured_stop(micro_bundle,
                                                                                             bundle_v2):
    v1 = micro_bundle[-1]
    stop, key, v2 = bundle_v2
    manifest = verify_bundle(v2)  # the changelog is listed and checked like every file
    assert manifest["parent"]["name"] == v1.name and manifest["parent"]["bundle_version"] == "0.1.0"
    assert manifest["bundle_version"] == "0.1.1" and "changelog.json" in manifest["files"]
    log = json.loads((v2 / "changelog.json").read_text())
    assert log["areas_changed"] == [key]
    assert log["areas"][key]["stops_recaptured"] == [stop]
    assert log["stops"]["stops_added"] == log["stops"]["stops_removed"] == 0
    n_db = len(stop_fingerprints(tables.read_table(v1 / "db" / "images.parquet", "images")))
    assert log["stops"]["stops_kept"] == n_db - 1
    assert log["components"] == {"model": "kept", "index": "changed", "data": "changed"}
    assert set(log["map"]["per_area"]) <= {key}  # no runs came with the re-capture: nothing else may move
    assert "db/database_ipa.parquet" in log["files"]["changed"] and "models/describer.onnx" not in log["files"]["added"]
    assert manifest["changelog"]["areas_changed"] == [key]


def test_diff_of_a_bundle_with_itself_is_empty_and_bundles_of_two_sites_are_refused(micro_bundle, tmp_path):
    v1 = micro_bundle[-1]
    view = read_view(v1, verify_bundle(v1))
    d = diff_bundles(view, view)
    assert d["areas_changed"] == [] and d["map"]["cells_changed"] == 0
    assert set(d["components"].values()) == {"kept"} and d["files"]["changed"] == []
    other = read_view(v1, verify_bundle(v1))
    other.site = "another"
    with pytest.raises(DiffError, match="another"):
        diff_bundles(view, other)


def test_the_cli_diff_prints_the_change_and_both_bundles_figures(micro_bundle, bundle_v2, tmp_path):
    cfg, ing, *_, v1 = micro_bundle
    stop, key, v2 = bundle_v2
    res = CliRunner().invoke(app, ["diff", str(v1), str(v2.with_name(v2.name + ".tar.gz")), "--data", str(ing),
                                   "--out", str(tmp_path / "d"), "--config", "ci"])
    assert res.exit_code == 0, res.output
    assert key in res.output and "re-captured" in res.output and "On the same images" in res.output
    d = json.loads((tmp_path / "d" / "diff.json").read_text())
    fa, fb = d["figures"]["a"], d["figures"]["b"]
    assert fa["all"]["images"] == fb["all"]["images"] > 0
    # v1's database holds the site's views of the stop; v2's the mirrored ones: only v1 sees them unchanged.
    assert fa["areas"][key]["same_place_similarity"] == pytest.approx(1.0, abs=1e-5)
    assert fb["areas"][key]["same_place_similarity"] < fa["areas"][key]["same_place_similarity"]
    assert d["to"]["name"] == v2.name


def test_a_parent_of_another_site_or_of_the_same_version_is_refused(micro_bundle, tmp_path):
    cfg, ing, model, index, v1 = micro_bundle
    with pytest.raises(InputError, match="version"):
        run_export(cfg, inputs={"parent": v1, "model": model, "index": index, "data": ing},
                   outputs={"out": tmp_path / "b"})
    assert not (tmp_path / "b").exists()
    fake = tmp_path / "fake"
    shutil.copytree(v1, fake)
    m = json.loads((fake / "manifest.json").read_text())
    m.update(site="another", bundle_version="0.0.9")
    (fake / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match="another"):
        run_export(cfg, inputs={"parent": fake, "model": model, "index": index, "data": ing},
                   outputs={"out": tmp_path / "b"})
    assert not (tmp_path / "b").exists()
