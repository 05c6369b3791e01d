"""`extract --reuse`: after `update`, only the new images are described, and the result is a full extraction's."""

from __future__ import annotations

import json
import shutil

import pyarrow.parquet as pq
import pytest

from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.io.image_reuse import HASHES_FILE
from pipeline.retrieval.extract import run_extract
from pipeline.retrieval.reuse import ReusedDescriptors
from pipeline.update.site_update import run_update
from tests.fixtures.recapture import mirrored_stop


def recaptured_stop(ing, out):
    """An ingested site holding the first stop of `ing` with its views mirrored (new files, same poses), no runs."""
    stop = tables.read_table(ing / "images.parquet", "images").column("stop_id")[0].as_py()
    out = mirrored_stop(ing, out, stop)
    return out, set(tables.read_table(out / "images.parquet", "images").column("image_id").to_pylist())


@pytest.fixture(scope="module")
def updated_site(micro_site, tmp_path_factory):
    cfg, ing, _ = micro_site
    root = tmp_path_factory.mktemp("reuse")
    new, new_ids = recaptured_stop(ing, root / "new")
    return run_update(cfg, inputs={"site_db": ing, "new_data": new}, outputs={"out": root / "v2"},
                      progress=False), new_ids


def test_an_updated_site_is_extracted_from_its_new_images_only_and_as_a_full_run_would(
        micro_site, micro_extraction, updated_site, tmp_path):
    cfg, _, model = micro_site
    v2, new_ids = updated_site
    fresh = run_extract(cfg, inputs={"model": model, "data": v2}, outputs={"out": tmp_path / "fresh"},
                        progress=False)
    reused = run_extract(cfg, inputs={"model": model, "data": v2, "reuse": micro_extraction},
                         outputs={"out": tmp_path / "reused"}, progress=False)
    for name in ("ipa.parquet", "rpa.parquet", "catalog.parquet", HASHES_FILE):
        assert pq.read_table(reused / name).equals(pq.read_table(fresh / name)), name
    rep = json.loads((reused / "report.json").read_text())
    # The update replaced every stop of the mirrored stop's area; only the mirrored views are new files.
    assert rep["computed_images"] == len(new_ids) == 6
    assert rep["reuse"] == {"from": str(micro_extraction), "describer_matches": True,
                            "reused_images": rep["images"] - 6}
    assert json.loads((fresh / "report.json").read_text())["computed_images"] == rep["images"]


def test_rows_are_reused_only_for_the_same_describer_and_an_old_extraction_is_refused(micro_extraction, tmp_path):
    key = json.loads((micro_extraction / "report.json").read_text())["describer_sha256"]
    assert len(ReusedDescriptors(micro_extraction, key)) > 0
    other = ReusedDescriptors(micro_extraction, "0" * 64)
    assert not other.matches and len(other) == 0
    old = tmp_path / "old"
    shutil.copytree(micro_extraction, old)
    (old / HASHES_FILE).unlink()
    with pytest.raises(InputError, match="cannot be reused"):
        ReusedDescriptors(old, key)
