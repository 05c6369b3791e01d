"""Bundle verification: what the runtime refuses, on small hand-made bundles (no detector needed)."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from pipeline.bundle.export import archive_of, write_archive, write_manifest
from pipeline.runtime.bundle import BundleError, open_bundle, peek_site, read_manifest, verify_bundle

SETTINGS = """filter: {}
retrieval: {top_n: 4, rerank: true, query_regions: 10, candidate_weights: [4.0, 3.0, 2.0, 1.0]}
laser: {angle_min: -1.5, angle_increment: 0.01, range_max: 10.0, base_from_laser: [0.0, 0.0, 0.0]}
"""


@pytest.fixture
def bundle(tmp_path) -> Path:
    root = tmp_path / "site-1.0"
    (root / "db").mkdir(parents=True)
    (root / "map").mkdir()
    (root / "db" / "a.bin").write_bytes(bytes(range(256)) * 4)
    (root / "map" / "map.yaml").write_text("image: map.pgm\n")
    (root / "filter.yaml").write_text(SETTINGS)
    write_manifest(root, {"bundle_version": "1.0", "site": "site"})
    return root


def _archive(root: Path) -> Path:
    return write_archive(root, archive_of(root), root.name)


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
    _edit_manifest(bundle, lambda m: m["files"].__setitem__(entry, {"sha256": "0" * 64, "size": 1}))
    with pytest.raises(BundleError, match="not a relative path inside the bundle"):
        verify_bundle(bundle)


def test_a_symlink_out_of_the_bundle_is_refused(bundle):
    """A listed data file that is a link is refused, even one whose target has the listed content."""
    secret = bundle.parent / "secret.bin"
    (bundle / "db" / "a.bin").rename(secret)
    os.symlink(secret, bundle / "db" / "a.bin")
    with pytest.raises(BundleError, match=r"db/a\.bin: a symbolic link \(to .*secret\.bin\); .*could point outside"):
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
    with pytest.raises(BundleError, match=r"hostile\.tar\.gz: member '\.\./escape\.txt' would be written outside"):
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


# --- a hostile or damaged bundle: every refusal a BundleError naming what the user gave ------------------------


def test_a_manifest_that_is_a_link_is_refused_even_to_a_valid_manifest(bundle, tmp_path):
    outside = tmp_path / "elsewhere.json"
    (bundle / "manifest.json").rename(outside)
    os.symlink(outside, bundle / "manifest.json")
    with pytest.raises(BundleError, match=r"site-1\.0/manifest\.json: a symbolic link \(to .*elsewhere\.json\)"):
        verify_bundle(bundle)
    with pytest.raises(BundleError, match="manifest.json: a symbolic link"):
        read_manifest(bundle)
    assert peek_site(bundle) is None


def test_a_linked_directory_an_unlisted_link_and_a_special_file_are_refused(bundle, tmp_path):
    import shutil

    copy = tmp_path / "db-copy"
    shutil.copytree(bundle / "db", copy)
    shutil.rmtree(bundle / "db")
    os.symlink(copy, bundle / "db")  # the same files, through a linked directory
    with pytest.raises(BundleError, match=r"site-1\.0/db: a symbolic link"):
        verify_bundle(bundle)
    (bundle / "db").unlink()
    shutil.copytree(copy, bundle / "db")
    verify_bundle(bundle)
    os.symlink(bundle / "filter.yaml", bundle / "map" / "extra.yaml")  # unlisted, pointing inside
    with pytest.raises(BundleError, match=r"map/extra\.yaml: a symbolic link"):
        verify_bundle(bundle)
    (bundle / "map" / "extra.yaml").unlink()
    os.mkfifo(bundle / "db" / "pipe")
    with pytest.raises(BundleError, match=r"db/pipe: not a regular file"):
        verify_bundle(bundle)


@pytest.mark.parametrize(("change", "expected"), [
    (lambda m: m["files"].__setitem__("db/a.bin", 3), r"entry 'db/a\.bin': is 3, not \{\"sha256\""),
    (lambda m: m["files"]["db/a.bin"].__setitem__("sha256", 7), r"entry 'db/a\.bin': sha256 7 is not 64 hex"),
    (lambda m: m["files"]["db/a.bin"].__setitem__("sha256", None), r"entry 'db/a\.bin': sha256 null is not"),
    (lambda m: m["files"]["db/a.bin"].__setitem__("size", "1024"), r"entry 'db/a\.bin': size \"1024\" is not a"),
    (lambda m: m["files"]["db/a.bin"].__setitem__("size", True), r"entry 'db/a\.bin': size true is not a"),
    (lambda m: m["files"]["db/a.bin"].__setitem__("size", -1), r"entry 'db/a\.bin': size -1 is not a"),
    (lambda m: m["files"]["db/a.bin"].pop("size"), r"entry 'db/a\.bin': size null is not a"),
    (lambda m: m.__setitem__("files", ["db/a.bin"]), r"no 'files' table"),
    (lambda m: m.__setitem__("site", ["x"]), r"'site' is a list of 1 items, not a str"),
    (lambda m: m.__setitem__("provenance", "x"), r"'provenance' is \"x\", not a dict"),
    (lambda m: m.__setitem__("provenance", {"inputs": [1]}), r"'provenance\.inputs' is a list of 1 items"),
    (lambda m: m.pop("schema_version"), r"no schema_version"),
    (lambda m: m.__setitem__("schema_version", "x.1"), r"schema_version 'x\.1' is not a version number"),
])
def test_manifest_entries_of_the_wrong_type_are_refused_naming_manifest_and_entry(bundle, change, expected):
    _edit_manifest(bundle, change)
    with pytest.raises(BundleError, match=r"site-1\.0/manifest\.json: " + expected) as err:
        verify_bundle(bundle)
    assert "export the bundle again" in str(err.value) or "schema" in str(err.value)


@pytest.mark.parametrize("text", [b"{", b"\xff\xfe{}", b"[" * 100_000, b"[]", b"null"])
def test_a_manifest_that_is_not_a_json_object_is_refused(bundle, text):
    (bundle / "manifest.json").write_bytes(text)
    with pytest.raises(BundleError, match=r"manifest\.json: (not valid JSON|no 'files' table)"):
        verify_bundle(bundle)


def _cut(archive: Path, keep: float) -> Path:
    data = archive.read_bytes()
    archive.write_bytes(data[: int(len(data) * keep)])
    return archive


@pytest.mark.parametrize(("damage", "expected"), [
    (lambda a: _cut(a, 0.5), r"cannot unpack: truncated"),
    (lambda a: _cut(a, 0.95), r"cannot unpack: truncated"),
    (lambda a: a.write_bytes(b""), r"cannot unpack: not a readable tar\.gz"),
    (lambda a: a.write_bytes(b"not an archive at all"), r"cannot unpack: not a readable tar\.gz"),
    (lambda a: a.write_bytes(a.read_bytes()[:40] + bytes(200) + a.read_bytes()[240:]), r"cannot unpack: "),
])
def test_a_truncated_or_corrupt_archive_is_a_bundle_error_naming_it(bundle, tmp_path, monkeypatch, damage, expected):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    archive = _archive(bundle)
    damage(archive)
    with pytest.raises(BundleError) as err:
        open_bundle(archive)
    text = str(err.value)
    assert text.startswith(f"{archive}: ") and re.search(expected, text), text
    assert "EOFError" not in text and "unexpected" not in text
    assert list((tmp_path / "tmp").iterdir()) == []  # the temporary it unpacked into is gone again
    assert peek_site(archive) in ("site", None)  # only names a default output: never raises


def _tar(path: Path, *members: tuple[tarfile.TarInfo, bytes | None]) -> Path:
    with tarfile.open(path, "w:gz") as tar:
        for info, data in members:
            if data is not None:
                info.size = len(data)
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


def _info(name: str, kind: bytes = tarfile.REGTYPE, link: str = "") -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, link
    if kind == tarfile.DIRTYPE:
        info.mode = 0o755
    return info


@pytest.mark.parametrize(("member", "expected"), [
    ((_info("site-1.0/db/a.bin", tarfile.SYMTYPE, "/etc/passwd"), None), r"is a link \(to '/etc/passwd'\)"),
    ((_info("site-1.0/db/b.bin", tarfile.SYMTYPE, "a.bin"), None), r"is a link \(to 'a\.bin'\)"),
    ((_info("site-1.0/db/c.bin", tarfile.LNKTYPE, "site-1.0/filter.yaml"), None), r"is a link"),
    ((_info("site-1.0/../escape.txt"), b"x"), r"would be written outside the bundle"),
    ((_info("/tmp/escape.txt"), b"x"), r"would be written outside the bundle"),
    ((_info("site-1.0/dev", tarfile.CHRTYPE), None), r"is a device, pipe or other special file"),
    ((_info("site-1.0/fifo", tarfile.FIFOTYPE), None), r"is a device, pipe or other special file"),
    ((_info("other/x.txt"), b"x"), r"an archive of one bundle directory expected"),
    ((_info("loose.txt"), b"x"), r"a file beside the bundle directory"),
])
def test_an_archive_member_that_is_a_link_a_device_or_escapes_is_refused(tmp_path, member, expected):
    archive = _tar(tmp_path / "hostile.tar.gz", (_info("site-1.0", tarfile.DIRTYPE), None),
                   (_info("site-1.0/filter.yaml"), SETTINGS.encode()), member)
    with pytest.raises(BundleError, match=rf"^{re.escape(str(archive))}: .*{expected}"):
        open_bundle(archive, tmp_path / "unpacked")
    assert not (tmp_path / "unpacked" / "site-1.0").exists()  # refused before anything was written
    assert not (tmp_path / "escape.txt").exists()


def test_a_damaged_file_inside_an_archive_is_named_by_archive_and_member(bundle, tmp_path):
    (bundle / "db" / "a.bin").write_bytes(bytes(1024))  # same size, other content
    archive = _archive(bundle)
    with pytest.raises(BundleError) as err:
        open_bundle(archive, tmp_path / "unpacked")
    assert str(err.value).startswith(f"{archive} (site-1.0/db/a.bin): sha256 differs")
    assert str(tmp_path / "unpacked") not in str(err.value)


@pytest.mark.parametrize(("section", "value", "expected"), [  # `expected`: what follows "filter.yaml"
    ("filter", {"min_particles": "many"}, r", section filter: invalid configuration\n  - key 'min_particles': "
                                          r"Input should be a valid integer.*'many'"),
    ("filter", "junk", r": section 'filter' is \"junk\", not a mapping of settings"),
    ("laser", {"angle_min": -1.5, "angle_increment": "abc", "range_max": 10.0, "base_from_laser": [0, 0, 0]},
     r", section laser: angle_increment is \"abc\", not a positive finite number"),
    ("laser", {"angle_min": -1.5, "angle_increment": 0.01, "range_max": 10.0, "base_from_laser": [0, 0]},
     r", section laser: base_from_laser is a list of 2 items, not \[x, y, yaw\]"),
    ("retrieval", {"top_n": 0}, r", section retrieval: top_n is 0, not a positive integer"),
    ("retrieval", {"candidate_weights": ["a"]}, r", section retrieval: candidate_weights is a list of 1 items"),
    ("retrieval", None, r": no 'retrieval' section"),
])
def test_a_bad_value_in_filter_yaml_is_refused_naming_the_file_and_key(bundle, tmp_path, section, value, expected):
    import yaml

    from pipeline.runtime.localizer import Localizer

    settings = yaml.safe_load(SETTINGS)
    settings[section] = value
    (bundle / "filter.yaml").write_text(yaml.safe_dump(settings))
    write_manifest(bundle, {"bundle_version": "1.0", "site": "site"})
    with pytest.raises(BundleError, match=rf"^{re.escape(str(bundle))}/filter\.yaml{expected}"):
        open_bundle(bundle)
    with pytest.raises(BundleError, match=rf"site-1\.0/filter\.yaml{expected}"):  # the runtime's way in
        Localizer.from_bundle(bundle)
    archive = _archive(bundle)
    with pytest.raises(BundleError, match=rf"^{re.escape(str(archive))} \(site-1\.0/filter\.yaml\){expected}"):
        open_bundle(archive, tmp_path / "unpacked")


def test_peek_site_reads_a_plain_site_name_only(bundle):
    assert peek_site(bundle) == "site" and peek_site(_archive(bundle)) == "site"
    _edit_manifest(bundle, lambda m: m.__setitem__("site", "../../etc"))
    assert peek_site(bundle) is None
    assert peek_site(bundle.parent / "missing.tar.gz") is None


def test_the_archive_lists_the_manifest_first(bundle):
    with tarfile.open(_archive(bundle)) as tar:
        assert tar.getnames()[:2] == ["site-1.0", "site-1.0/manifest.json"]


@pytest.mark.parametrize("argv", [
    ["check", "{archive}", "{data}", "--out", "{out}", "--no-localize"],
    ["localize", "{data}", "--bundle", "{archive}", "--out", "{out}"],
    ["evaluate", "{archive}", "{data}"],  # the default --out is named from the manifest
    ["diff", "{archive}", "{archive}"],
])
def test_the_cli_refuses_a_truncated_archive_naming_it(bundle, tmp_path, monkeypatch, argv):
    from typer.testing import CliRunner

    from stages.app import app

    archive = _cut(_archive(bundle), 0.5)
    (tmp_path / "data").mkdir()
    monkeypatch.chdir(tmp_path)
    args = [a.format(archive=archive, data=tmp_path / "data", out=tmp_path / "out") for a in argv]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1, res.output
    assert f"error: {archive}: cannot unpack: truncated" in res.output, res.output
    assert "unexpected" not in res.output and "Traceback" not in res.output, res.output
    assert not (tmp_path / "out").exists() and not (tmp_path / "reports").exists()
