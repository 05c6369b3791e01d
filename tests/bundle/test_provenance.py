"""A bundle's provenance: inputs hashed by their content, DVC's lock quoted only when DVC built it."""

from __future__ import annotations

import hashlib

import yaml

from pipeline.bundle.provenance import provenance, tree_sha256


def _tree(tmp_path):
    d = tmp_path / "models" / "detector"
    (d / "sub").mkdir(parents=True)
    (d / "weights.bin").write_bytes(b"\x00\x01")
    (d / "sub" / "config.json").write_text("{}")
    return d


def test_tree_hash_is_the_sha256_of_sorted_path_and_file_hash_lines(tmp_path):
    d = _tree(tmp_path)
    lines = "".join(f"{rel}\0{hashlib.sha256(data).hexdigest()}\n"
                    for rel, data in sorted([("sub/config.json", b"{}"), ("weights.bin", b"\x00\x01")]))
    assert tree_sha256(d) == (hashlib.sha256(lines.encode()).hexdigest(), 2)
    before = tree_sha256(d)[0]
    (d / "weights.bin").write_bytes(b"\x00\x02")
    assert tree_sha256(d)[0] != before  # content, not names or sizes
    assert tree_sha256(d / "weights.bin")[0] == hashlib.sha256(b"\x00\x02").hexdigest()


def test_outside_dvc_says_so_and_quotes_no_lock(tmp_path, monkeypatch):
    d = _tree(tmp_path)
    (tmp_path / "dvc.lock").write_text(yaml.safe_dump({"stages": {"train": {"outs": [
        {"path": "models/detector", "md5": "abc.dir"}]}}}))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("DVC_STAGE", raising=False)
    p = provenance({"model": d})
    assert p["built_by"] == "siteloc export, outside DVC" and "no dvc.lock entry" in p["note"]
    assert "dvc_md5" not in p["inputs"]["model"] and p["inputs"]["model"]["files"] == 2


def test_under_dvc_each_input_carries_its_lock_md5(tmp_path, monkeypatch):
    d = _tree(tmp_path)
    (tmp_path / "dvc.lock").write_text(yaml.safe_dump({"schema": "2.0", "stages": {"train": {"outs": [
        {"path": "models/detector", "md5": "abc.dir", "size": 3}]}}}))
    monkeypatch.setenv("DVC_STAGE", "export")
    monkeypatch.setenv("DVC_ROOT", str(tmp_path))
    p = provenance({"model": d, "other": tmp_path / "models"})
    assert p["built_by"] == "dvc repro (stage export)"
    assert p["inputs"]["model"]["dvc_md5"] == "abc.dir"
    assert p["inputs"]["other"]["dvc_md5"] is None  # not an output DVC tracks: no md5 is made up
