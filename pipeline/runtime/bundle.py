"""Reading a deployable bundle safely (no torch, no pickle): every file checked before anything is used.

A bundle is a directory `<site>-<version>/` written by `siteloc export`, or its `.tar.gz`:

    manifest.json      schema and bundle versions, site, created, code version, effective config,
                       dvc.lock hash, and every other file with its sha256 and size (written last)
    filter.yaml        filter settings, retrieval settings, laser geometry and mount, camera size
    map/               map.yaml + map.pgm (ROS map_server)
    db/                whitened database descriptors and poses (Parquet), whitening arrays (npz), the
                       database images' stops and labels (images.parquet)
    evaluation/        baseline.json: the bundle's own figures per area (`siteloc check` compares with them)
    changelog.*        with a parent bundle: what changed against it (`pipeline.bundle.diff`)
    models/            describer.onnx (image -> map, proposals, detections) and describer.json

`verify_bundle` refuses, naming the file and the fix: a missing manifest, an unknown major schema, a
listed file that is missing, of another size or another sha256, a path that leaves the bundle (absolute,
`..`, or a symlink pointing out), and files the manifest does not list.
"""

from __future__ import annotations

import hashlib
import json
import tarfile
import tempfile
from pathlib import Path, PurePosixPath

from pipeline.errors import SitelocError

SCHEMA_VERSION = "1.0"
MANIFEST = "manifest.json"


class BundleError(SitelocError):
    """A bundle that must not be used; the message names the file and what to do."""


def sha256_of(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def safe_member(root: Path, rel: str) -> Path:
    """The path of a manifest entry inside `root`; BundleError when it would leave the bundle."""
    p = PurePosixPath(rel)
    if not rel or p.is_absolute() or "\\" in rel or any(part in ("..", "") for part in p.parts) or rel.startswith("/"):
        raise BundleError(f"{root / MANIFEST}: entry '{rel}' is not a relative path inside the bundle; "
                          f"the bundle was altered: export it again")
    path = root / p
    try:
        path.resolve().relative_to(root.resolve())
    except ValueError:
        raise BundleError(f"{path}: points outside the bundle (a link?); export the bundle again") from None
    return path


def _schema_major(version: str, where: Path) -> int:
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        raise BundleError(f"{where}: schema_version '{version}' is not a version number") from None


def read_manifest(root: Path) -> dict:
    path = root / MANIFEST
    if not root.is_dir():
        raise BundleError(f"{root}: not a bundle directory (give the directory `siteloc export` wrote, or its .tar.gz)")
    if not path.is_file():
        raise BundleError(f"{path}: missing; an export that did not finish, or not a bundle: run `siteloc export`")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BundleError(f"{path}: not valid JSON ({exc}); export the bundle again") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
        raise BundleError(f"{path}: no 'files' table; export the bundle again")
    major = _schema_major(manifest.get("schema_version", ""), path)
    if major != _schema_major(SCHEMA_VERSION, path):
        raise BundleError(f"{path}: bundle schema {manifest.get('schema_version')}, this siteloc reads "
                          f"{SCHEMA_VERSION.split('.')[0]}.x; export the bundle with this version of siteloc")
    return manifest


def verify_bundle(root: Path) -> dict:
    """The manifest, once every listed file is present, inside the bundle, of its size and sha256."""
    root = Path(root)
    manifest = read_manifest(root)
    listed = set()
    for rel, entry in sorted(manifest["files"].items()):
        path = safe_member(root, rel)
        listed.add(path.resolve())
        if not path.is_file():
            raise BundleError(f"{path}: listed in the manifest but missing; copy the whole bundle again")
        size = path.stat().st_size
        if size != entry.get("size"):
            raise BundleError(f"{path}: {size} bytes, the manifest says {entry.get('size')} (truncated or altered); "
                              f"copy the bundle again")
        if sha256_of(path) != entry.get("sha256"):
            raise BundleError(f"{path}: sha256 differs from the manifest (altered); copy or export the bundle again")
    extra = [p for p in root.rglob("*") if (p.is_file() or p.is_symlink()) and p.name != MANIFEST
             and p.resolve() not in listed]
    if extra:
        raise BundleError(f"{extra[0]}: not listed in the manifest ({len(extra)} such files); "
                          f"remove them or export the bundle again")
    return manifest


def open_bundle(path: Path, workdir: Path | None = None) -> Path:
    """A verified bundle directory: `path` itself, or a `.tar.gz` unpacked (tar's 'data' filter: no links
    out, no absolute paths, no devices) into `workdir` (a new temporary directory by default)."""
    path = Path(path)
    if path.is_file() and path.name.endswith((".tar.gz", ".tgz")):
        target = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="siteloc-bundle-"))
        try:
            with tarfile.open(path, "r:gz") as tar:
                tops = {PurePosixPath(m.name).parts[0] for m in tar.getmembers() if m.name}
                if len(tops) != 1:
                    raise BundleError(f"{path}: an archive of one bundle directory expected, found {sorted(tops)}")
                tar.extractall(target, filter="data")
        except (tarfile.TarError, OSError) as exc:
            raise BundleError(f"{path}: cannot unpack ({exc}); download or export it again") from None
        path = target / tops.pop()
    verify_bundle(path)
    return path
