"""Conversion cache: parsed models and decoded textures as `.npz` of plain arrays plus a JSON index.

Why: reading ~40 OBJs out of 130 MB of zips and decoding their textures takes seconds; loading the arrays
back takes a fraction of that. No pickles anywhere (`np.load(..., allow_pickle=False)` reads every file);
metadata (names, creators, licences, colours) lives in `index.json`. Every write is atomic (temporary file
+ os.replace), so a killed process or two processes building at once never leave a torn file: the worst
case is a record converted twice.

Validity: each record stores the sha256 of the source archive(s) it came from. An archive's sha256 is
recomputed only when its size or mtime changed (hashing 130 MB each run would cost more than it saves),
and a change of the converter's settings or format version drops the whole index.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.atomic import atomic_file, write_text_atomic
from pipeline.io.hashing import sha256_file  # noqa: F401 - the asset cache's name for it
from pipeline.sitegen.asset_types import MeshPart, Model, TextureInfo

FORMAT = 1
INDEX = "index.json"


@dataclass
class Archive:
    """A source of catalog files: a `.sh3f`/`.jar` zip, or a directory holding the jar's extracted files."""

    name: str  # catalog name: "Scopia", ..., "sweethome3d.jar"
    package: str  # Debian package it comes from
    path: Path
    _read: Callable[[str], bytes] | None = None

    def exists(self) -> bool:
        return self.fingerprint_path().is_file()

    def fingerprint_path(self) -> Path:
        """The file whose bytes identify the content (an extracted jar directory has a SOURCE.json)."""
        return self.path / "SOURCE.json" if self.path.is_dir() else self.path

    def read(self, member: str) -> bytes:
        """Bytes of `member` (path inside the archive); KeyError when it is not there."""
        if self._read is None:
            if self.path.is_dir():
                root = self.path

                def read_dir(name: str) -> bytes:
                    try:
                        return (root / name.lstrip("/")).read_bytes()
                    except (FileNotFoundError, IsADirectoryError) as exc:
                        raise KeyError(name) from exc

                self._read = read_dir
            else:
                import zipfile

                from pipeline.sitegen.obj_catalog import zip_reader

                self._read = zip_reader(zipfile.ZipFile(self.path))
        return self._read(member)

    def describe(self, member: str) -> str:
        """Provenance text: package, archive (the jar by name even when read from its extracted copy), member."""
        label = self.name if self.path.is_dir() else self.path.name
        return f"Debian package {self.package}: {label}/{member.lstrip('/')}"


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


class ConversionCache:
    """Models and textures by key, valid while their source hash matches."""

    def __init__(self, root: Path, settings: dict) -> None:
        self.root = Path(root)
        self.settings = settings
        self.dirty = False
        self.index = self._read_index()

    def _fresh(self) -> dict:
        return {"format": FORMAT, "settings": self.settings, "archives": {}, "models": {}, "skipped": {},
                "textures": {}}

    def _read_index(self) -> dict:
        try:
            data = json.loads((self.root / INDEX).read_text())
        except (OSError, ValueError):
            return self._fresh()
        if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("settings") != self.settings:
            return self._fresh()
        for key in ("archives", "models", "skipped", "textures"):
            data.setdefault(key, {})
        return data

    def archive_sha256(self, archive: Archive) -> str:
        path = archive.fingerprint_path()
        stat = path.stat()
        known = self.index["archives"].get(str(path))
        if known and known["size"] == stat.st_size and known["mtime_ns"] == stat.st_mtime_ns:
            return known["sha256"]
        sha = sha256_file(path)
        self.index["archives"][str(path)] = {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "sha256": sha}
        self.dirty = True
        return sha

    # -- models

    def model(self, key: str, source_sha: str) -> Model | None:
        record = self.index["models"].get(key)
        if not record or record.get("source_sha") != source_sha:
            return None
        try:
            with np.load(self.root / record["file"], allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError, KeyError):
            return None
        parts = []
        for i, meta in enumerate(record["parts"]):
            tex = meta.get("texture")
            parts.append(MeshPart(
                positions=arrays[f"p{i}_positions"], normals=arrays[f"p{i}_normals"], uvs=arrays[f"p{i}_uvs"],
                texture=arrays[f"t{tex}"] if tex is not None else None, colour=tuple(meta["colour"]),
                opacity=float(meta["opacity"]), role=meta.get("role", ""),
            ))
        span = record.get("wall_span_y")
        return Model(key=record["key"], cls=record["cls"], name=record["name"], creator=record["creator"],
                     license=record["license"], source=record["source"], size=tuple(record["size"]),
                     parts=tuple(parts), procedural=False, kind=record["kind"], elevation=record["elevation"],
                     wall_span_y=tuple(span) if span else None)

    def store_model(self, model: Model, source_sha: str, files_sha256: dict[str, str]) -> None:
        arrays: dict[str, np.ndarray] = {}
        texture_ids: dict[int, int] = {}
        parts = []
        for i, part in enumerate(model.parts):
            arrays[f"p{i}_positions"] = np.ascontiguousarray(part.positions, dtype=np.float32)
            arrays[f"p{i}_normals"] = np.ascontiguousarray(part.normals, dtype=np.float32)
            arrays[f"p{i}_uvs"] = np.ascontiguousarray(part.uvs, dtype=np.float32)
            tex = None
            if part.texture is not None:
                tex = texture_ids.setdefault(id(part.texture), len(texture_ids))
                arrays[f"t{tex}"] = np.ascontiguousarray(part.texture, dtype=np.uint8)
            parts.append({"colour": list(part.colour), "opacity": part.opacity, "role": part.role, "texture": tex})
        rel = f"models/{_safe(model.key)}.npz"
        self._write_npz(rel, arrays)
        self.index["models"][model.key] = {
            "key": model.key, "cls": model.cls, "kind": model.kind, "name": model.name, "creator": model.creator,
            "license": model.license, "source": model.source, "size": list(model.size),
            "elevation": model.elevation, "wall_span_y": list(model.wall_span_y) if model.wall_span_y else None,
            "triangles": model.n_triangles, "parts": parts, "file": rel, "source_sha": source_sha,
            "files_sha256": files_sha256,
        }
        self.index["skipped"].pop(model.key, None)
        self.dirty = True

    def skipped(self, key: str, source_sha: str) -> str | None:
        record = self.index["skipped"].get(key)
        return record["reason"] if record and record.get("source_sha") == source_sha else None

    def store_skip(self, key: str, source_sha: str, reason: str) -> None:
        self.index["skipped"][key] = {"reason": reason, "source_sha": source_sha}
        self.dirty = True

    # -- textures

    def texture(self, key: str, source_sha: str) -> tuple[TextureInfo, np.ndarray] | None:
        record = self.index["textures"].get(key)
        if not record or record.get("source_sha") != source_sha:
            return None
        try:
            with np.load(self.root / record["file"], allow_pickle=False) as data:
                image = data["image"]
        except (OSError, ValueError, KeyError):
            return None
        tile = record.get("tile_size_m")
        info = TextureInfo(role=record["role"], name=record["name"], creator=record["creator"],
                           license=record["license"], source=record["source"],
                           tile_size_m=tuple(tile) if tile else None)
        return info, image

    def store_texture(self, key: str, info: TextureInfo, image: np.ndarray, source_sha: str) -> None:
        rel = f"textures/{_safe(key)}.npz"
        self._write_npz(rel, {"image": np.ascontiguousarray(image, dtype=np.uint8)})
        self.index["textures"][key] = {
            "role": info.role, "name": info.name, "creator": info.creator, "license": info.license,
            "source": info.source, "tile_size_m": list(info.tile_size_m) if info.tile_size_m else None,
            "file": rel, "source_sha": source_sha,
        }
        self.dirty = True

    # -- writing

    def _write_npz(self, rel: str, arrays: dict[str, np.ndarray]) -> None:
        with atomic_file(self.root / rel, "wb") as fh:
            np.savez(fh, **arrays)

    def save(self) -> None:
        if self.dirty:
            self.root.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.root / INDEX, json.dumps(self.index, indent=1, sort_keys=True) + "\n")
            self.dirty = False


def combined_sha(*shas: str) -> str:
    """One hash for a record built from several archives (a poster: the jar's frame + a picture)."""
    return hashlib.sha256("\n".join(shas).encode()).hexdigest() if len(shas) > 1 else shas[0]


def env_path(name: str) -> Path | None:
    value = os.environ.get(name)
    return Path(value).expanduser() if value else None
