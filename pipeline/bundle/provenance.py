"""What a bundle was built from: each input's content hash, the code, and whether DVC built it.

`export` records this in manifest.json. Every input (detector, database, ingest, sequence model, area
prior) gets a sha256 over its files, so two bundles can be compared input by input without the data.
When `dvc repro` runs the export stage (DVC sets DVC_STAGE), the inputs' entries in dvc.lock are current
(DVC has just checked them), and their md5 is recorded beside ours; outside DVC the manifest says so
plainly instead of quoting a lock that may describe other outputs.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

import yaml

from pipeline.runtime.bundle import sha256_of


def tree_sha256(path: Path) -> tuple[str, int]:
    """sha256 of a file, or of a folder's sorted (relative path, file sha256) lines; and the file count."""
    path = Path(path)
    if path.is_file():
        return sha256_of(path), 1
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file())
    for p in files:
        h.update(f"{p.relative_to(path).as_posix()}\0{sha256_of(p)}\n".encode())
    return h.hexdigest(), len(files)


def _git(*args: str, cwd: Path) -> str | None:
    try:
        return subprocess.run(["git", *args], capture_output=True, text=True, timeout=10, cwd=cwd,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def _lock_outs(root: Path) -> dict[str, str]:
    """{output path: md5} of every stage in root/dvc.lock (empty when there is none or it is unreadable)."""
    try:
        lock = yaml.safe_load((root / "dvc.lock").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    return {o["path"]: o.get("md5") for stage in (lock.get("stages") or {}).values()
            for o in stage.get("outs", []) if isinstance(o, dict) and "path" in o}


def provenance(inputs: dict[str, Path | None], *, code_dir: Path | None = None) -> dict:
    """The manifest's `provenance` entry for a bundle built now from `inputs` (name -> path)."""
    code_dir = Path(code_dir or Path(__file__).resolve().parent)
    stage = os.environ.get("DVC_STAGE")
    root = Path(os.environ.get("DVC_ROOT", Path.cwd()))
    lock = _lock_outs(root) if stage else {}
    entries = {}
    for name, path in inputs.items():
        if path is None:
            continue
        digest, files = tree_sha256(Path(path))
        entry = {"path": str(path), "sha256": digest, "files": files}
        if stage:
            try:
                rel = Path(path).resolve().relative_to(root.resolve()).as_posix()
            except ValueError:
                rel = None
            entry["dvc_md5"] = lock.get(rel) if rel else None
        entries[name] = entry
    status = _git("status", "--porcelain", "--untracked-files=no", cwd=code_dir)
    return {
        "built_by": f"dvc repro (stage {stage})" if stage else "siteloc export, outside DVC",
        "note": ("dvc.lock recorded each input's md5 (dvc_md5) when this bundle was built" if stage else
                 "built outside DVC: no dvc.lock entry describes this bundle; the inputs' sha256 do"),
        "git_commit": _git("rev-parse", "HEAD", cwd=code_dir),
        "git_dirty": bool(status) if status is not None else None,
        "inputs": entries,
    }
