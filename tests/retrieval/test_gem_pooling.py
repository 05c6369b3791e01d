"""`retrieval.pooling: gem`: the IPA as the generalized mean of the map, from `extract` through `build-index`
and `export` to the runtime describer; closed forms on made-up maps, then the micro reference site."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.retrieval.descriptors import (
    check_pooling,
    describe_graph_outputs,
    describe_outputs,
    ipa_descriptor,
    recorded_pooling,
)
from pipeline.retrieval.whitening import l2_normalize
from tests.fixtures.log_capture import Warnings


def test_gem_closed_forms_and_sum_unchanged():
    rng = np.random.default_rng(0)
    fmap = rng.normal(size=(6, 4, 5)).astype(np.float32)
    s = fmap.sum(axis=(1, 2))
    np.testing.assert_array_equal(ipa_descriptor(fmap), l2_normalize(s))  # the paper's IPA, as before
    np.testing.assert_array_equal(ipa_descriptor(fmap, "sum", p=7.0), ipa_descriptor(fmap))  # p: gem only
    pos = np.abs(fmap) + 0.1
    mean = pos.reshape(6, -1).mean(axis=1)
    np.testing.assert_allclose(ipa_descriptor(pos, "gem", p=1.0), mean / np.linalg.norm(mean), atol=1e-6)
    mx = pos.reshape(6, -1).max(axis=1)
    np.testing.assert_allclose(ipa_descriptor(pos, "gem", p=200.0), mx / np.linalg.norm(mx), atol=2e-2)
    cube = np.cbrt((pos.astype(np.float64) ** 3).reshape(6, -1).mean(axis=1))
    got = ipa_descriptor(pos, "gem")  # p = 3 by default
    assert got.dtype == np.float32 and got.shape == (6,)
    np.testing.assert_allclose(got, cube / np.linalg.norm(cube), rtol=1e-6)
    neg = ipa_descriptor(-pos, "gem")  # clamped at 1e-6, never a fractional power of a negative number
    assert np.all(np.isfinite(neg))
    np.testing.assert_allclose(neg, np.full(6, 1 / np.sqrt(6)), rtol=1e-6)
    with pytest.raises(ValueError, match="pooling must be one of"):
        ipa_descriptor(fmap, "max")


def _outputs(rng):
    det_map, bb_map = rng.random((8, 5, 6), dtype=np.float32), rng.random((10, 3, 3), dtype=np.float32)
    proposals = np.float32([[0, 0, 40, 30], [50, 40, 95, 71]])
    outs = [det_map, proposals, np.float32([0.9, 0.8]), np.float32([[10, 10, 60, 50]]), np.float32([0.7]),
            np.int64([3])]
    return outs, bb_map


def test_graph_outputs_pool_as_the_describer_json_says_and_an_older_one_sums():
    rng = np.random.default_rng(1)
    outs, bb_map = _outputs(rng)
    meta = {"scale": [1.0, 1.0], "stride": 16.0}
    old = describe_graph_outputs(outs, meta, rpa_proposals=2, rpa_min_score=0.3)  # no ipa_pooling: sum
    np.testing.assert_array_equal(old.ipa, ipa_descriptor(outs[0]))
    gem = describe_graph_outputs(outs, {**meta, "ipa_pooling": "gem", "gem_p": 3.0}, rpa_proposals=2,
                                 rpa_min_score=0.3)
    np.testing.assert_array_equal(gem.ipa, ipa_descriptor(outs[0], "gem", 3.0))
    assert np.abs(gem.ipa - old.ipa).max() > 1e-3  # not the sum
    np.testing.assert_array_equal(gem.rpa, old.rpa)  # the regions pool as before
    p2 = describe_graph_outputs(outs, {**meta, "ipa_pooling": "gem", "gem_p": 2.0}, rpa_proposals=2,
                                rpa_min_score=0.3)
    np.testing.assert_array_equal(p2.ipa, ipa_descriptor(outs[0], "gem", 2.0))
    np.testing.assert_array_equal(  # gem_p absent: 3
        describe_graph_outputs(outs, {**meta, "ipa_pooling": "gem"}, rpa_proposals=2, rpa_min_score=0.3).ipa, gem.ipa)
    # a backbone's map is pooled alike; a head's output is the IPA whatever the pooling
    meta["retrieval_backbone"] = {"stride": 32, "outputs": ["backbone_map"]}
    d = describe_graph_outputs([*outs, bb_map], {**meta, "ipa_pooling": "gem"}, rpa_proposals=2, rpa_min_score=0.3)
    np.testing.assert_array_equal(d.ipa, ipa_descriptor(bb_map, "gem"))
    glob = rng.standard_normal(12).astype(np.float32)
    meta["retrieval_backbone"]["outputs"] = ["backbone_map", "backbone_ipa"]
    d = describe_graph_outputs([*outs, bb_map, glob], {**meta, "ipa_pooling": "gem"}, rpa_proposals=2,
                               rpa_min_score=0.3)
    np.testing.assert_allclose(d.ipa, glob / np.linalg.norm(glob), rtol=1e-6)
    want = describe_outputs(bb_map, (1.0, 1.0), 32, *outs[1:], rpa_proposals=2, rpa_min_score=0.3,
                            global_descriptor=glob)
    np.testing.assert_array_equal(d.ipa, want.ipa)


def test_a_report_records_its_pooling_and_another_is_refused(tmp_path):
    assert recorded_pooling(None) == recorded_pooling({}) == ("sum", None)  # before pooling was recorded
    assert recorded_pooling({"ipa_pooling": "sum", "gem_p": 5.0}) == ("sum", None)
    assert recorded_pooling({"ipa_pooling": "gem"}) == ("gem", 3.0)
    report = tmp_path / "report.json"
    check_pooling(report, "sum", 3.0)  # no report: sum
    report.write_text(json.dumps({"images": 3}))
    check_pooling(report, "sum", 9.0)
    with pytest.raises(InputError, match="pooled otherwise") as err:
        check_pooling(report, "gem", 3.0)
    assert "retrieval.pooling=sum" in str(err.value) and str(report) in str(err.value)
    report.write_text(json.dumps({"ipa_pooling": "gem", "gem_p": 4.0}))
    check_pooling(report, "gem", 4.0)
    for pooling, p in (("sum", 4.0), ("gem", 3.0)):
        with pytest.raises(InputError) as err:
            check_pooling(report, pooling, p)
        assert "--set retrieval.pooling=gem --set retrieval.gem_p=4.0" in str(err.value)


# --- the micro reference site -------------------------------------------------------------------------------

GEM_SETS = ["retrieval.pooling=gem", "retrieval.include_runs=false", "export.archive=false", "export.parity_images=2"]


@pytest.fixture(scope="module")
def gem(micro_site, tmp_path_factory):
    """(config, ingest, detector, extraction, index, bundle) of the micro site with `retrieval.pooling: gem`."""
    from pipeline.bundle.export import run_export
    from pipeline.config import load_config
    from pipeline.retrieval.database import run_build_index
    from pipeline.retrieval.extract import run_extract
    from tests.conftest import MICRO_SETS

    _, ing, model = micro_site
    root = tmp_path_factory.mktemp("gem")
    cfg = load_config("ci", [*MICRO_SETS, *GEM_SETS])
    ex = run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": root / "d"}, progress=False)
    index = run_build_index(cfg, inputs={"descriptors": ex}, outputs={"out": root / "index"})
    bundle = run_export(cfg, inputs={"model": model, "index": index, "data": ing}, outputs={"out": root / "bundles"})
    return cfg, ing, model, ex, index, bundle


def _rows(directory, kind):
    from pipeline.io import tables

    t = tables.read_table(directory / f"{kind}.parquet", kind)
    return t.column("image_id").to_pylist(), tables.descriptor_matrix(t), t


def test_extract_pools_the_maps_by_gem_and_records_it(gem, micro_extraction):
    from pipeline.detection.inference import detector_features, load_detector, load_image
    from pipeline.retrieval.extract import describe

    cfg, ing, model, ex, _, _ = gem
    report = json.loads((ex / "report.json").read_text())
    assert (report["engine"], report["ipa_pooling"], report["gem_p"]) == ("onnx", "gem", 3.0)
    summed = json.loads((micro_extraction / "report.json").read_text())
    assert summed["ipa_pooling"] == "sum" and "gem_p" not in summed
    assert report["describer_sha256"] != summed["describer_sha256"]
    (graph,) = report["onnx"]["graphs"].values()
    assert graph["ipa_pooling"] == "gem" and graph["parity"]["max_differences"]["ipa_abs"] <= 1e-3
    ids, ipa, _ = _rows(ex, "ipa")
    sum_ids, sum_ipa, _ = _rows(micro_extraction, "ipa")
    det, r = load_detector(model, device="cpu"), cfg.retrieval
    for k in (0, len(ids) // 2):
        image = load_image(ing / ids[k])
        fmap = detector_features(det, [image])[0].feature_map.numpy()  # the torch twin of the graph's map
        np.testing.assert_allclose(ipa[k], ipa_descriptor(fmap, "gem", 3.0), atol=1e-4)
        twin = describe(det, [image], r.rpa_proposals, r.rpa_min_score, pooling="gem", gem_p=3.0)[0]
        np.testing.assert_allclose(twin.ipa, ipa_descriptor(fmap, "gem"), atol=1e-6)
        assert np.abs(ipa[k] - sum_ipa[sum_ids.index(ids[k])]).max() > 1e-3  # not the sum the default extracts
    # the regions are the same either way
    rid, rpa, rt = _rows(ex, "rpa")
    sid, srpa, st = _rows(micro_extraction, "rpa")
    a = [i for i, v in enumerate(rid) if v == ids[0]]
    b = [i for i, v in enumerate(sid) if v == ids[0]]
    assert rt.take(a).drop_columns(["descriptor"]).equals(st.take(b).drop_columns(["descriptor"]))
    np.testing.assert_allclose(rpa[a], srpa[b], atol=1e-5)


def test_reuse_takes_no_rows_of_an_extraction_pooled_otherwise(gem, micro_extraction):
    from pipeline.retrieval.reuse import ReusedDescriptors, describer_key
    from pipeline.sitegen.asset_cache import sha256_file

    cfg, _, model, ex, _, _ = gem
    r = cfg.retrieval
    settings = {"rpa_proposals": r.rpa_proposals, "rpa_min_score": r.rpa_min_score, "engine": "onnx"}
    weights = sha256_file(model / "weights.safetensors")
    sum_key = describer_key(weights, settings)
    gem_key = describer_key(weights, {**settings, "pooling": {"name": "gem", "p": 3.0}})
    assert sum_key == json.loads((micro_extraction / "report.json").read_text())["describer_sha256"]
    assert gem_key == json.loads((ex / "report.json").read_text())["describer_sha256"]
    assert len(ReusedDescriptors(ex, gem_key, pooling=("gem", 3.0))) > 0
    for earlier, key, now, was in ((micro_extraction, gem_key, ("gem", 3.0), "sum"),
                                   (ex, sum_key, ("sum", 3.0), "gem (p 3.0)")):
        with Warnings("pipeline.retrieval.reuse") as log:
            reused = ReusedDescriptors(earlier, key, pooling=now)
        assert not reused.matches and len(reused) == 0
        assert reused.differs.startswith(f"retrieval.pooling: {was} there")
        assert f"extracted with retrieval.pooling {was}" in log.text and "described afresh" in log.text
    with Warnings("pipeline.retrieval.reuse") as log:  # another pooling p only
        assert ReusedDescriptors(ex, "0" * 64, pooling=("gem", 2.0)).differs is not None
    assert "--set retrieval.pooling=gem --set retrieval.gem_p=3.0" in log.text


def test_the_bundle_carries_gem_and_the_runtime_describes_as_the_extraction(gem, micro_extraction, tmp_path):
    from typer.testing import CliRunner

    from pipeline.bundle.export import run_export
    from pipeline.config import load_config
    from pipeline.detection.onnx_export import TOLERANCE
    from pipeline.retrieval.evaluate import run_evaluate_retrieval
    from pipeline.runtime.describer import OnnxDescriber
    from stages.app import app
    from tests.conftest import MICRO_SETS

    _, ing, model, ex, index, bundle = gem
    assert json.loads((index / "report.json").read_text())["ipa_pooling"] == "gem"
    meta = json.loads((bundle / "models" / "describer.json").read_text())
    assert (meta["ipa_pooling"], meta["gem_p"]) == ("gem", 3.0)
    assert meta["parity"]["max_differences"]["ipa_abs"] <= TOLERANCE["descriptor_abs"]
    runtime = OnnxDescriber(bundle / "models" / "describer.onnx", bundle / "models" / "describer.json")
    ids, ipa, _ = _rows(ex, "ipa")
    for k in (0, len(ids) // 2):
        np.testing.assert_allclose(runtime.describe(ing / ids[k]).ipa, ipa[k], atol=1e-5)
    # export, query and evaluate-retrieval --queries refuse to mix poolings, naming the fix
    sums = load_config("ci", [*MICRO_SETS, "export.archive=false"])
    with pytest.raises(InputError, match="pooled otherwise") as err:
        run_export(sums, inputs={"model": model, "index": index, "data": ing}, outputs={"out": tmp_path / "b"})
    assert "--set retrieval.pooling=gem --set retrieval.gem_p=3.0" in str(err.value)
    assert not (tmp_path / "b").exists()
    res = CliRunner().invoke(app, ["query", str(index), str(ing / ids[0]), "--model", str(model), "-c", "ci",
                                   *[a for s in MICRO_SETS for a in ("--set", s)]])
    assert res.exit_code == 1 and "--set retrieval.pooling=gem" in res.output
    with pytest.raises(InputError, match="pool their IPA differently"):
        run_evaluate_retrieval(sums, inputs={"descriptors": micro_extraction, "data": ing, "query_descriptors": ex,
                                             "query_data": ing}, outputs={"out": tmp_path / "ev"}, progress=False)


def test_a_ray_actor_pools_as_its_graphs_info_says(gem, tmp_path):
    """`extract --engine ray`: the actors describe through the graphs `onnx_describer` exported, whose info
    (describer.json) carries the pooling; run here without Ray, on the bundle's graph."""
    from pipeline.io import tables
    from pipeline.retrieval.extract_ray import ChunkDescriber

    _, ing, _, ex, _, bundle = gem
    meta = json.loads((bundle / "models" / "describer.json").read_text())
    ids, ipa, _ = _rows(ex, "ipa")
    graphs = {f"{meta['image_hw'][1]}x{meta['image_hw'][0]}": (str(bundle / "models" / "describer.onnx"), meta)}
    ChunkDescriber(str(tmp_path), str(ing), graphs)({"chunk": np.array([0]), "image_ids": [ids[:2]]})
    got = tables.descriptor_matrix(tables.read_table(tmp_path / "ipa-00000.parquet", "ipa"))
    np.testing.assert_allclose(got, ipa[:2], atol=1e-5)
