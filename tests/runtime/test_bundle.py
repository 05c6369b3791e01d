"""Bundle verification: what the runtime refuses, on small hand-made bundles (no detector needed)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from pipeline.bundle.export import _archive, write_manifest
from pipeline.runtime.bundle import BundleError, open_bundle, verify_bundle


@pytest.fixture
def bundle(tmp_path) -> Path:
    root = tmp_path / "site-1.0"
    (root / "db").mkdir(parents=True)
    (root / "map").mkdir()
    (root / "db" / "a.bin").write_bytes(bytes(range(256)) * 4)
    (root / "map" / "map.yaml").write_text("image: map.pgm\n")
    (root / "filter.yaml").write_text("filter: {}\n")
    write_manifest(root, {"bundle_version": "1.0", "site": "site"})
    return root


def _edit_manifest(root: Path, change) -> None:
    m = json.loads((root / "manifest.json").read_text())
    change(m)
    (root / "manifest.json").write_text(json.dumps(m))


def test_a_written_bundle_verifies_and_lists_every_file_with_its_hash(bundle):
    m = verify_bundle(bundle)
    assert sorted(m["files"]) == ["db/a.bin", "filter.yaml", "map/map.yaml"]
    assert m["files"]["db/a.bin"]["size"] == 1024
    import hashlib

    assert m["files"]["db/a.bin"]["sha256"] == hashlib.sha256((bundle / "db" / "a.bin").read_bytes()).hexdigest()


def test_an_altered_file_is_refused(bundle):
    data = bytearray((bundle / "db" / "a.bin").read_bytes())
    data[100] ^= 1  # same size, one bit flipped
    (bundle / "db" / "a.bin").write_bytes(bytes(data))
    with pytest.raises(BundleError, match="a.bin: sha256 differs"):
        verify_bundle(bundle)


def test_a_truncated_file_is_refused(bundle):
    (bundle / "db" / "a.bin").write_bytes(b"short")
    with pytest.raises(BundleError, match="5 bytes, the manifest says 1024"):
        verify_bundle(bundle)


def test_a_missing_file_and_a_missing_manifest_are_refused(bundle):
    (bundle / "map" / "map.yaml").unlink()
    with pytest.raises(BundleError, match="map.yaml: listed in the manifest but missing"):
        verify_bundle(bundle)
    (bundle / "manifest.json").unlink()
    with pytest.raises(BundleError, match="manifest.json: missing"):
        verify_bundle(bundle)


def test_an_unlisted_file_is_refused(bundle):
    (bundle / "db" / "extra.parquet").write_bytes(b"x")
    with pytest.raises(BundleError, match="extra.parquet: not listed"):
        verify_bundle(bundle)


@pytest.mark.parametrize("entry", ["../outside.txt", "/etc/passwd", "db/../../outside.txt", "db\\a.bin", ""])
def test_paths_escaping_the_bundle_are_refused(bundle, entry):
    (bundle.parent / "outside.txt").write_text("x")
    _edit_manifest(bundle, lambda m: m["files"].__setitem__(entry, {"sha256": "0", "size": 1}))
    with pytest.raises(BundleError, match="not a relative path inside the bundle"):
        verify_bundle(bundle)


def test_a_symlink_out_of_the_bundle_is_refused(bundle):
    secret = bundle.parent / "secret.txt"
    secret.write_text("secret")
    (bundle / "db" / "a.bin").unlink()
    os.symlink(secret, bundle / "db" / "a.bin")
    with pytest.raises(BundleError, match="points outside the bundle"):
        verify_bundle(bundle)


def test_another_major_schema_is_refused_a_minor_one_accepted(bundle):
    _edit_manifest(bundle, lambda m: m.__setitem__("schema_version", "1.7"))
    verify_bundle(bundle)
    _edit_manifest(bundle, lambda m: m.__setitem__("schema_version", "2.0"))
    with pytest.raises(BundleError, match="bundle schema 2.0, this siteloc reads 1.x"):
        verify_bundle(bundle)


def test_an_archive_round_trips_and_a_hostile_one_is_refused(bundle, tmp_path):
    archive = _archive(bundle)
    opened = open_bundle(archive, tmp_path / "unpacked")
    assert opened == tmp_path / "unpacked" / bundle.name
    assert verify_bundle(opened)["files"] == verify_bundle(bundle)["files"]
    hostile = tmp_path / "hostile.tar.gz"
    with tarfile.open(hostile, "w:gz") as tar:
        info = tarfile.TarInfo("../escape.txt")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(BundleError, match="cannot unpack"):
        open_bundle(hostile, tmp_path / "h")
    assert not (tmp_path / "escape.txt").exists()


def test_the_runtime_modules_import_without_torch():
    code = ("import sys; import pipeline.runtime.localizer, pipeline.runtime.describer, pipeline.runtime.bundle, "
            "pipeline.runtime.amcl, pipeline.retrieval.database, pipeline.retrieval.search, "
            "pipeline.runtime.areaprior, pipeline.prior.model, pipeline.descriptors.compression; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "False"


def test_parity_matching_pairs_equal_boxes_in_any_order_and_accepts_no_detections():
    import numpy as np

    from pipeline.detection.onnx_export import _match_regions, matched_share

    a = np.array([[0, 0, 10, 10], [5, 5, 20, 20], [1, 1, 2, 2]], np.float32)
    b = a[[2, 0, 1]] + 0.1  # reordered (tied scores), within tolerance
    pairs = _match_regions(a, b, 0.5)
    assert sorted(pairs) == [(0, 1), (1, 2), (2, 0)] and matched_share(pairs, a) == 1.0
    assert matched_share(_match_regions(a, b + 5, 0.5), a) == 0.0
    assert matched_share([], np.zeros((0, 4))) == 1.0  # an untrained detector may detect nothing at all
