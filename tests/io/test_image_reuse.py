"""`frame-features --reuse` and `prior features --reuse`: only changed images are encoded, and the output is a
full run's."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.compute as pc
import pytest
from PIL import Image

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.io.image_reuse import HASHES_FILE
from pipeline.sitegen.asset_cache import sha256_file

PRIOR_SETS = ["prior.weights=null", "prior.input_size=64", "prior.device=cpu"]


def _alter(site, image_ids):
    """Rewrite these images of a copied site mirrored with a dark quarter (new content), and their sha256 in
    images.parquet."""
    for i in image_ids:
        path = site / i
        img = Image.open(path)
        img.load()
        path.unlink()  # a hard link to the original site's file: write a new one
        img = img.convert("RGB").transpose(Image.FLIP_LEFT_RIGHT)
        img.paste((0, 0, 0), (0, 0, img.width // 2, img.height // 2))
        img.save(path)
    images = tables.read_table(site / "images.parquet", "images")
    shas = [sha256_file(site / i) if i in set(image_ids) else s
            for i, s in zip(images.column("image_id").to_pylist(), images.column("sha256").to_pylist(), strict=True)]
    tables.write_table(site / "images.parquet", images.set_column(images.schema.get_field_index("sha256"), "sha256",
                                                                  [shas]), "images")


def test_frame_features_reuse_encodes_only_the_changed_frames(micro_frames, tmp_path):
    from pipeline.sequence.frames import run_frame_features

    cfg, ing, earlier = micro_frames
    site = tmp_path / "site"
    shutil.copytree(ing, site)
    t = tables.read_table(earlier / "frames.parquet", "frames")
    changed = t.column("image_id").to_pylist()[:3]
    _alter(site, changed)
    reused = run_frame_features(cfg, inputs={"data": site, "reuse": earlier}, outputs={"out": tmp_path / "r"},
                                progress=False)
    full = run_frame_features(cfg, inputs={"data": site}, outputs={"out": tmp_path / "f"}, progress=False)
    rep = json.loads((reused / "report.json").read_text())
    assert rep["computed_frames"] == 3 and rep["reuse"]["reused_frames"] == t.num_rows - 3
    assert rep["reuse"]["encoder_matches"] and rep["encoder_sha256"] == json.loads(
        (full / "report.json").read_text())["encoder_sha256"]
    a, b = (tables.read_table(d / "frames.parquet", "frames") for d in (reused, full))
    assert a.drop_columns(["descriptor"]).equals(b.drop_columns(["descriptor"]))
    # ONNX, one frame per run of the graph: the same bytes give the same logits, reused or computed.
    assert np.array_equal(tables.descriptor_matrix(a), tables.descriptor_matrix(b))
    old = tables.descriptor_matrix(t)
    assert not np.allclose(tables.descriptor_matrix(a)[:3], old[:3])  # the altered frames were encoded anew
    assert tables.read_table(reused / HASHES_FILE, "image_hashes").equals(
        tables.read_table(full / HASHES_FILE, "image_hashes"))


def test_frame_features_of_another_encoder_reuse_nothing(micro_frames, tmp_path):
    from pipeline.sequence.frames import run_frame_features

    cfg, ing, earlier = micro_frames
    other = cfg.model_copy(update={"sequence": cfg.sequence.model_copy(update={"frame_size": 48})})
    out = run_frame_features(other, inputs={"data": ing, "reuse": earlier}, outputs={"out": tmp_path / "r"},
                             progress=False)
    rep = json.loads((out / "report.json").read_text())
    assert rep["reuse"] == {"from": str(earlier), "encoder_matches": False, "reused_frames": 0}
    assert rep["computed_frames"] == rep["frames"]
    with pytest.raises(InputError, match="cannot be reused"):
        run_frame_features(cfg, inputs={"data": ing, "reuse": ing}, outputs={"out": tmp_path / "x"}, progress=False)
    assert not (tmp_path / "x").exists()


def test_prior_features_reuse_encodes_only_the_changed_images(micro_site, tmp_path):
    from pipeline.prior.features import read_layers, run_prior_features

    _, ing, _ = micro_site
    cfg = load_config("ci", PRIOR_SETS)
    earlier = run_prior_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "e"}, progress=False)
    site = tmp_path / "site"
    shutil.copytree(ing, site)
    images = tables.read_table(site / "images.parquet", "images")
    stop = images.column("stop_id")[0].as_py()
    changed = images.filter(pc.equal(images.column("stop_id"), stop)).column("image_id").to_pylist()
    _alter(site, changed)
    reused = run_prior_features(cfg, inputs={"data": site, "reuse": earlier}, outputs={"out": tmp_path / "r"},
                                progress=False)
    full = run_prior_features(cfg, inputs={"data": site}, outputs={"out": tmp_path / "f"}, progress=False)
    rep = json.loads((reused / "report.json").read_text())
    assert rep["computed_images"] == len(changed) == 6 and rep["reuse"]["reused_images"] == images.num_rows - 6
    (ma, ra, _), (mb, rb, _), (_, re, _) = read_layers(reused), read_layers(full), read_layers(earlier)
    assert ma == mb
    first = [k for k, i in enumerate(ma["image_id"]) if i in set(changed)]
    for layer in ra:
        # Torch in batches: a batch of other images may round the last bits otherwise.
        np.testing.assert_allclose(ra[layer], rb[layer], rtol=0, atol=1e-6)
    # The altered images were encoded anew (random weights: the early layers tell images apart).
    assert any(not np.allclose(ra[layer][first], re[layer][first]) for layer in ra)
