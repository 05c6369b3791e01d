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

`verify_bundle` refuses, naming the file and the fix: a missing manifest, one that is a link, not JSON or
not of the expected shape (entries with a sha256 and a size), an unknown major schema, a listed file that is
missing, of another size or another sha256, a path that leaves the bundle (absolute, `..`), any link or
special file inside the bundle (exports never write them), and files the manifest does not list.
`open_bundle` unpacks an archive only when every member is a plain file or directory inside one top
directory, and reports a truncated or corrupt archive as a BundleError naming it; it also checks
filter.yaml (`read_settings`). Every message names the path the user gave: for an archive, the archive
and the member (`bundles/x.tar.gz (x/db/a.bin): ...`), not the temporary directory it was unpacked into.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import math
import os
import re
import shutil
import stat
import tarfile
import tempfile
import zlib
from pathlib import Path, PurePosixPath

from pipeline.errors import SitelocError, excerpt

SCHEMA_VERSION = "1.0"
MANIFEST = "manifest.json"
SETTINGS = "filter.yaml"
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz")
MANIFEST_LIMIT = 64 << 20  # bytes: a manifest lists files; one this large was not written by export
_SHA256 = re.compile(r"[0-9a-f]{64}")
ARCHIVE_ERRORS = (tarfile.TarError, EOFError, zlib.error, OSError)


class BundleError(SitelocError):
    """A bundle that must not be used; the message names the file and what to do."""


def sha256_of(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def shown(root: Path, rel: str = "", archive: str | Path | None = None) -> str:
    """How a bundle file is named in messages: its path, or for an unpacked archive `archive (member)`."""
    if archive is None:
        return str(root / rel) if rel else str(root)
    return f"{archive} ({root.name}/{rel})" if rel else str(archive)


def _link_target(path: Path) -> str:
    try:
        return excerpt(os.readlink(path), 200)
    except OSError:
        return "?"


def _refuse_link(path: Path, name: str) -> None:
    """BundleError when `path` is a symbolic link: a bundle never holds one, and one may point out of it."""
    if path.is_symlink():
        raise BundleError(f"{name}: a symbolic link (to {_link_target(path)}); a bundle holds plain files only and a "
                          f"link could point outside it: copy the bundle again without links, or export it again")


def safe_member(root: Path, rel: str, archive: str | Path | None = None) -> Path:
    """The path of a manifest entry inside `root`; BundleError when it would leave the bundle or is (or
    passes through) a link."""
    parts = rel.split("/") if isinstance(rel, str) else []
    if (not parts or rel.startswith("/") or "\\" in rel or any(p in ("", ".", "..") for p in parts)
            or PurePosixPath(rel).is_absolute()):
        raise BundleError(f"{shown(root, MANIFEST, archive)}: entry '{excerpt(rel)}' is not a relative path inside "
                          f"the bundle; the bundle was altered: export it again")
    path = root
    for i, part in enumerate(parts):
        path = path / part
        _refuse_link(path, shown(root, "/".join(parts[: i + 1]), archive))
    try:
        path.resolve().relative_to(root.resolve())
    except ValueError:
        raise BundleError(f"{shown(root, rel, archive)}: points outside the bundle; export the bundle again") from None
    return path


def _schema_major(version, where: str) -> int:
    if version is None or version == "":
        raise BundleError(f"{where}: no schema_version; not a bundle manifest: export the bundle again")
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        raise BundleError(f"{where}: schema_version '{excerpt(version)}' is not a version number") from None


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _quote(value) -> str:
    """A short quotation of a value read from a bundle file (containers only described: they may be huge)."""
    if isinstance(value, dict | list):
        return f"a {'mapping' if isinstance(value, dict) else 'list'} of {len(value)} items"
    return excerpt(json.dumps(value, default=str))


_OPTIONAL_FIELDS = {"site": (str,), "bundle_version": (str, int, float), "created": (str,), "code_version": (str,),
                    "provenance": (dict,), "config": (dict,), "inputs": (dict,), "database": (dict,),
                    "parent": (dict,), "changelog": (dict,)}


def _check_entries(manifest: dict, where: str) -> None:
    """Every field the readers use has the type export writes (a hand-edited manifest is refused here, not
    met as an AttributeError later)."""
    for key, types in _OPTIONAL_FIELDS.items():
        v = manifest.get(key)
        if v is not None and (not isinstance(v, types) or isinstance(v, bool)):
            raise BundleError(f"{where}: '{key}' is {_quote(v)}, not a "
                              f"{' or '.join(t.__name__ for t in types)}; the manifest was altered: export the "
                              f"bundle again")
    inputs = (manifest.get("provenance") or {}).get("inputs")
    if inputs is not None and not (isinstance(inputs, dict) and all(isinstance(v, dict) for v in inputs.values())):
        raise BundleError(f"{where}: 'provenance.inputs' is {_quote(inputs)}, not a mapping of inputs; the manifest "
                          f"was altered: export the bundle again")
    for rel, entry in manifest["files"].items():
        problem = None
        if not isinstance(entry, dict):
            problem = f"is {_quote(entry)}, not {{\"sha256\": ..., \"size\": ...}}"
        elif not isinstance(entry.get("sha256"), str) or not _SHA256.fullmatch(entry["sha256"]):
            problem = f"sha256 {_quote(entry.get('sha256'))} is not 64 hex digits"
        elif not _is_int(entry.get("size")) or entry["size"] < 0:
            problem = f"size {_quote(entry.get('size'))} is not a number of bytes"
        if problem:
            raise BundleError(f"{where}: entry '{excerpt(rel)}': {problem}; the manifest was altered: export the "
                              f"bundle again")


def read_manifest(root: Path, archive: str | Path | None = None) -> dict:
    """The manifest of the bundle directory `root`, refused unless a plain JSON file of the expected shape.

    `archive`: the .tar.gz `root` was unpacked from, named in messages instead of `root`.
    """
    root = Path(root)
    where = shown(root, MANIFEST, archive)
    if root.is_file() and root.name.endswith(ARCHIVE_SUFFIXES):
        raise BundleError(f"{root}: an archive; this needs the bundle directory: unpack it first (tar xzf {root})")
    if not root.is_dir():
        raise BundleError(f"{shown(root, '', archive)}: not a bundle directory (give the directory `siteloc export` "
                          f"wrote, or its .tar.gz)")
    path = root / MANIFEST
    _refuse_link(path, where)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise BundleError(f"{where}: missing; an export that did not finish, or not a bundle: run `siteloc export`"
                          ) from None
    except OSError as exc:
        raise BundleError(f"{where}: cannot read ({exc.strerror}); copy the bundle again") from None
    if not stat.S_ISREG(st.st_mode):
        raise BundleError(f"{where}: not a regular file; not a bundle: run `siteloc export`")
    if st.st_size > MANIFEST_LIMIT:
        raise BundleError(f"{where}: {st.st_size} bytes, more than any manifest export writes "
                          f"({MANIFEST_LIMIT >> 20} MiB); export the bundle again")
    try:
        manifest = json.loads(path.read_bytes())
    except OSError as exc:
        raise BundleError(f"{where}: cannot read ({exc.strerror}); copy the bundle again") from None
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise BundleError(f"{where}: not valid JSON ({excerpt(exc, 120)}); export the bundle again") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
        raise BundleError(f"{where}: no 'files' table; export the bundle again")
    major = _schema_major(manifest.get("schema_version"), where)
    if major != _schema_major(SCHEMA_VERSION, where):
        raise BundleError(f"{where}: bundle schema {excerpt(manifest.get('schema_version'))}, this siteloc reads "
                          f"{SCHEMA_VERSION.split('.')[0]}.x; export the bundle with this version of siteloc")
    _check_entries(manifest, where)
    return manifest


def _entries_on_disk(root: Path, archive: str | Path | None) -> set[str]:
    """Every file below `root` (posix, relative); BundleError for a link or a special file anywhere."""
    found = set()
    for top, dirs, files in os.walk(root):  # links to directories are listed in `dirs`, never followed
        base = Path(top)
        for name in dirs + files:
            path = base / name
            rel = path.relative_to(root).as_posix()
            _refuse_link(path, shown(root, rel, archive))
            if name in files:
                mode = path.lstat().st_mode
                if not stat.S_ISREG(mode):
                    raise BundleError(f"{shown(root, rel, archive)}: not a regular file (a device, pipe or socket); "
                                      f"remove it or export the bundle again")
                found.add(rel)
    return found


def verify_bundle(root: Path, archive: str | Path | None = None) -> dict:
    """The manifest, once every listed file is present, inside the bundle, a plain file of its size and
    sha256, and nothing else (no unlisted file, no link) is there. `archive`: as for `read_manifest`."""
    root = Path(root)
    manifest = read_manifest(root, archive)
    for rel, entry in sorted(manifest["files"].items()):
        path = safe_member(root, rel, archive)
        name = shown(root, rel, archive)
        try:
            st = path.stat()
        except FileNotFoundError:
            raise BundleError(f"{name}: listed in the manifest but missing; copy the whole bundle again") from None
        except OSError as exc:
            raise BundleError(f"{name}: cannot read ({exc.strerror}); copy the bundle again") from None
        if not stat.S_ISREG(st.st_mode):
            raise BundleError(f"{name}: listed in the manifest as a file but is not one; export the bundle again")
        if st.st_size != entry["size"]:
            raise BundleError(f"{name}: {st.st_size} bytes, the manifest says {entry['size']} (truncated or altered); "
                              f"copy the bundle again")
        try:
            digest = sha256_of(path)
        except OSError as exc:
            raise BundleError(f"{name}: cannot read ({exc.strerror}); copy the bundle again") from None
        if digest != entry["sha256"]:
            raise BundleError(f"{name}: sha256 differs from the manifest (altered); copy or export the bundle again")
    listed = {*manifest["files"], MANIFEST}
    extra = sorted(_entries_on_disk(root, archive) - listed)
    if extra:
        raise BundleError(f"{shown(root, extra[0], archive)}: not listed in the manifest ({len(extra)} such files); "
                          f"remove them or export the bundle again")
    return manifest


def _finite(v, *, positive: bool = False) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and (v > 0 or not positive)


def _refuse_value(where: str, key: str, value, want: str) -> None:
    raise BundleError(f"{where}: {key} is {_quote(value)}, not {want}; export the bundle again")


def read_settings(root: Path, archive: str | Path | None = None) -> dict:
    """filter.yaml of a verified bundle, refused (naming the file and the key) unless its sections have the
    shape export writes: the filter section valid for this siteloc, the laser geometry finite numbers."""
    import yaml

    where = shown(root, SETTINGS, archive)
    try:
        settings = yaml.safe_load((Path(root) / SETTINGS).read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise BundleError(f"{where}: not valid YAML ({excerpt(exc, 120)}); export the bundle again") from None
    except OSError as exc:
        raise BundleError(f"{where}: cannot read ({exc.strerror}); export the bundle again") from None
    for key in ("filter", "retrieval", "laser"):
        if not isinstance(settings, dict) or settings.get(key) is None:
            raise BundleError(f"{where}: no '{key}' section; export the bundle again")
        if not isinstance(settings[key], dict):
            _refuse_value(where, f"section '{key}'", settings[key], "a mapping of settings")
    from pydantic import ValidationError

    from pipeline.config import FilterConfig, format_validation_error

    try:
        FilterConfig.model_validate(settings["filter"])
    except ValidationError as err:
        raise BundleError(format_validation_error(f"{where}, section filter", err, FilterConfig)
                          + "\n  fix: export the bundle again with this version of siteloc "
                          "(`siteloc config show --explain filter` lists the settings)") from None
    las, r = settings["laser"], settings["retrieval"]
    for key, positive in (("angle_min", False), ("angle_increment", True), ("range_max", True)):
        if not _finite(las.get(key), positive=positive):
            _refuse_value(f"{where}, section laser", key, las.get(key), f"a {'positive ' * positive}finite number")
    if "beams" in las and not (_is_int(las["beams"]) and las["beams"] >= 1):  # optional: older bundles lack it
        _refuse_value(f"{where}, section laser", "beams", las["beams"], "a positive integer")
    mount = las.get("base_from_laser")
    if not (isinstance(mount, list) and len(mount) == 3 and all(_finite(v) for v in mount)):
        _refuse_value(f"{where}, section laser", "base_from_laser", mount, "[x, y, yaw] (finite numbers)")
    for key in ("top_n", "query_regions"):
        if key in r and not (_is_int(r[key]) and r[key] >= 1):
            _refuse_value(f"{where}, section retrieval", key, r[key], "a positive integer")
    weights = r.get("candidate_weights")
    if "candidate_weights" in r and not (isinstance(weights, list) and weights
                                         and all(_finite(v) and v >= 0 for v in weights)):
        _refuse_value(f"{where}, section retrieval", "candidate_weights", weights, "a list of weights (numbers >= 0)")
    for key in ("camera", "prior"):
        if settings.get(key) is not None and not isinstance(settings[key], dict):
            _refuse_value(where, f"section '{key}'", settings[key], "a mapping of settings")
    return settings


def _top_directory(path: Path, members: list[tarfile.TarInfo]) -> str:
    """The one directory an export's archive holds; BundleError for a member that is a link, a device,
    absolute, or climbing out with `..`."""
    tops = set()
    for m in members:
        name = m.name
        parts = [p for p in name.split("/") if p not in ("", ".")]
        if name.startswith("/") or ".." in parts or "\\" in name:
            raise BundleError(f"{path}: member '{excerpt(name)}' would be written outside the bundle; not an archive "
                              f"`siteloc export` wrote: download or export it again")
        if m.issym() or m.islnk():
            raise BundleError(f"{path}: member '{excerpt(name)}' is a link (to '{excerpt(m.linkname)}'); a bundle "
                              f"archive holds plain files and directories only: download or export it again")
        if not (m.isfile() or m.isdir()):
            raise BundleError(f"{path}: member '{excerpt(name)}' is a device, pipe or other special file; a bundle "
                              f"archive holds plain files and directories only: download or export it again")
        if parts:
            tops.add(parts[0])
            if len(parts) == 1 and not m.isdir():
                raise BundleError(f"{path}: member '{excerpt(name)}' is a file beside the bundle directory; an "
                                  f"archive of one bundle directory expected")
    if len(tops) != 1:
        raise BundleError(f"{path}: an archive of one bundle directory expected, found "
                          f"{excerpt(sorted(tops), 120) if tops else 'nothing'}; download or export it again")
    return tops.pop()


def _archive_problem(exc: BaseException) -> str:
    if isinstance(exc, EOFError):
        return "truncated: it ends before its last member (an interrupted download or copy?)"
    if isinstance(exc, zlib.error | gzip.BadGzipFile):
        return f"corrupt compressed data ({excerpt(exc, 120)})"
    if isinstance(exc, tarfile.FilterError):
        return f"member refused by tar's data filter ({excerpt(exc, 120)})"
    if isinstance(exc, tarfile.TarError):
        return f"not a readable tar.gz ({excerpt(exc, 120)})"
    return f"{exc.strerror or excerpt(exc, 120)}"


def unpack_archive(path: Path, target: Path) -> Path:
    """The bundle directory unpacked from the export archive `path` into `target`; every failure (truncated,
    corrupt, not an archive, a hostile member) a BundleError naming `path`."""
    try:
        with tarfile.open(path, "r:gz") as tar:
            members = tar.getmembers()  # reads the whole archive: a truncated one fails here, before writing
            top = _top_directory(path, members)
            need = sum(m.size for m in members)
            target.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(target).free
            if need > free:
                raise BundleError(f"{path}: unpacks to {need / 2**20:.0f} MiB, {free / 2**20:.0f} MiB free in "
                                  f"{target}; free space there or give the unpacked directory instead")
            tar.extractall(target, members=members, filter="data")
    except BundleError:
        raise
    except OSError as exc:
        if isinstance(exc, gzip.BadGzipFile) or exc.errno is None:
            raise BundleError(f"{path}: cannot unpack: {_archive_problem(exc)}; download or export it again") from None
        raise BundleError(f"{path}: cannot unpack into {target}: {exc.strerror}; free space or fix permissions "
                          f"there, or give the unpacked directory instead") from None
    except (tarfile.TarError, EOFError, zlib.error) as exc:
        raise BundleError(f"{path}: cannot unpack: {_archive_problem(exc)}; download or export it again") from None
    return target / top


def open_bundle(path: Path, workdir: Path | None = None) -> Path:
    """A verified bundle directory: `path` itself, or a `.tar.gz` unpacked (plain files and directories only,
    tar's 'data' filter besides) into `workdir` (a new temporary directory by default, removed again when
    the archive is refused). Its manifest, files and filter.yaml are checked; messages name `path`."""
    path = Path(path)
    if path.is_dir():
        verify_bundle(path)
        read_settings(path)
        return path
    if not path.exists():
        raise BundleError(f"{path}: no such bundle; give the directory `siteloc export` wrote, or its .tar.gz")
    if not (path.is_file() and path.name.endswith(ARCHIVE_SUFFIXES)):
        raise BundleError(f"{path}: not a bundle; give the directory `siteloc export` wrote, or its .tar.gz")
    made = workdir is None
    target = Path(tempfile.mkdtemp(prefix="siteloc-bundle-")) if made else Path(workdir)
    try:
        root = unpack_archive(path, target)
        verify_bundle(root, archive=path)
        read_settings(root, archive=path)
    except BaseException:
        if made:
            shutil.rmtree(target, ignore_errors=True)
        raise
    return root


def peek_site(path: Path) -> str | None:
    """The `site` a bundle's manifest names, without verifying it (only to name a default output): None when
    the manifest cannot be read, or names no plain site name (a link, a path, an odd character)."""
    path = Path(path)
    try:
        if path.is_dir():
            m = path / MANIFEST
            if m.is_symlink() or not m.is_file() or m.stat().st_size > MANIFEST_LIMIT:
                return None
            doc = json.loads(m.read_bytes())
        else:
            with tarfile.open(path, "r:gz") as tar:
                for member in tar:
                    if member.name.count("/") == 1 and member.name.endswith("/" + MANIFEST):
                        if not member.isfile() or member.size > MANIFEST_LIMIT:
                            return None
                        doc = json.loads(tar.extractfile(member).read())
                        break
                else:
                    return None
    except (*ARCHIVE_ERRORS, ValueError, RecursionError):
        return None
    site = doc.get("site") if isinstance(doc, dict) else None
    if isinstance(site, str) and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}", site):
        return site
    return None
