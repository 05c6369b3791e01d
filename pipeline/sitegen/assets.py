"""Real furniture meshes and photographic textures for the reference site, from Debian packages.

Sources (installed by `make setup`, see `install_assets`; nothing large is committed):
  - `sweethome3d-furniture` (apt, no dependencies): /usr/share/sweethome3d/furniture/*.sh3f, Sweet Home 3D
    furniture libraries: zips of OBJ/MTL/textures + `PluginFurnitureCatalog.properties`. Used here:
    BlendSwap-CC-0 (CC0), BlendSwap-CC-BY and Scopia (CC-BY 3.0), KatorLegaz (CC-BY 3.0 US).
  - `sweethome3d` (NOT installed: it pulls Java): its .deb is downloaded and only the jar's resources
    (eTeks' textures, door/window/frame/desk models, their catalogs) are extracted into
    `$SITELOC_ASSETS/sweethome3d-jar`. eTeks offers them under GPL-2+ or CC-BY 3.0; we use CC-BY 3.0.
Only CC0 / CC-BY models are picked (`MODEL_PICKS`, a curated list: office-like pieces per class, several per
class so repeated objects vary); a candidate over MAX_TRIANGLES is skipped for the next one (the renderer
runs on llvmpipe). Parsing is `obj_catalog` (why not trimesh: see there); results are cached by
`asset_cache`. Frames and array conventions: see `asset_types` (metres, z up, front -y, origin at the
centre of the footprint on the floor).

When the files are absent or broken, `load_assets` builds `procedural_assets` stand-ins, warns with
AssetFallbackWarning and sets `procedural` and `missing`, so a site still builds everywhere.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.sitegen import obj_catalog, procedural_assets
from pipeline.sitegen.asset_cache import Archive, ConversionCache, combined_sha, env_path
from pipeline.sitegen.asset_types import (
    ALLOWED_LICENSES,
    CC0,
    CC_BY,
    CC_BY_US,
    CLASSES,
    FURNITURE,
    AssetLibrary,
    AssetsUnavailableError,
    MeshPart,
    Model,
    TextureInfo,
)

__all__ = ["AssetLibrary", "MeshPart", "Model", "TextureInfo", "CLASSES", "FURNITURE", "ALLOWED_LICENSES",
           "AssetFallbackWarning", "AssetsUnavailableError", "load_assets", "asset_root", "describe"]

MAX_TRIANGLES = 20_000
CONVERTER_VERSION = 2  # bump when conversion output or cached metadata change: drops every cache
MODEL_TEXTURE_PX = 256
ROLE_TEXTURE_PX = 512
FURNITURE_DIR = Path("/usr/share/sweethome3d/furniture")
SYSTEM_JAR = Path("/usr/share/sweethome3d/sweethome3d.jar")
JAR = "sweethome3d.jar"
JAR_DIRNAME = "sweethome3d-jar"
JAR_RESOURCES = "com/eteks/sweethome3d/io/resources/"
JAR_TEXTURES = JAR_RESOURCES + "textures/"
JAR_FURNITURE_CATALOG = "com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties"
JAR_TEXTURE_CATALOG = "com/eteks/sweethome3d/io/DefaultTexturesCatalog.properties"
FURNITURE_PACKAGE = "sweethome3d-furniture"
JAR_PACKAGE = "sweethome3d"
CATALOG_LICENSES = {"BlendSwap-CC-0": CC0, "BlendSwap-CC-BY": CC_BY, "KatorLegaz": CC_BY_US, "Scopia": CC_BY,
                    JAR: CC_BY}
INSTALL_HINT = ("run `make setup`, or `sudo apt-get install sweethome3d-furniture` and "
                "`.venv/bin/python -m pipeline.sitegen.install_assets`")


class AssetFallbackWarning(UserWarning):
    """Procedural stand-ins replaced missing real assets (renders are less realistic)."""


@dataclass(frozen=True)
class Pick:
    cls: str  # one of CLASSES or "" (furniture)
    kind: str
    catalog: str
    folder: str  # model folder in the catalog (the jar: the OBJ's stem)


def _picks(cls: str, kind: str, *items: str) -> tuple[Pick, ...]:
    return tuple(Pick(cls, kind, *item.split("/", 1)) for item in items)


# In order of preference; every candidate within the triangle budget is used.
MODEL_PICKS: tuple[Pick, ...] = (
    *_picks("chair", "chair", "Scopia/office_chair", "BlendSwap-CC-BY/classSeat", "Scopia/plastic_chair",
            "Scopia/tubular_chair", "BlendSwap-CC-0/plasticChair", "KatorLegaz/dining-chair",
            "KatorLegaz/office-chair"),
    *_picks("door", "door", "Scopia/door", "Scopia/puerta", "Scopia/glass_door", "Scopia/glassDoor2", f"{JAR}/door"),
    *_picks("door", "door_exterior", "KatorLegaz/exterior-door-02", "Scopia/double_door", f"{JAR}/frontDoor"),
    *_picks("window", "window", "Scopia/window_2x1_medium_with_large_pane", "Scopia/window_2x4",
            "Scopia/turn-window", "KatorLegaz/window-08", f"{JAR}/window85x123", f"{JAR}/doubleWindow126x163"),
    *_picks("plant", "plant", "BlendSwap-CC-0/plant", "BlendSwap-CC-BY/decorativePlant", "Scopia/maceta",
            f"{JAR}/plant", "BlendSwap-CC-0/augalas", "BlendSwap-CC-BY/yuccaPlant"),
    *_picks("fire_extinguisher", "fire_extinguisher", "BlendSwap-CC-0/fireExtinguisher"),
    *_picks("trash_bin", "trash_bin", "BlendSwap-CC-0/dustbin", "KatorLegaz/bullet-trash-can",
            "KatorLegaz/recycling-bin"),
    *_picks("exit_sign", "exit_sign", "BlendSwap-CC-0/emergencySign"),
    *_picks("", "desk", "BlendSwap-CC-0/lbDesk", "BlendSwap-CC-BY/officeTable", "Scopia/wooden_office_pear_table_rect",
            "Scopia/glass_table_office", f"{JAR}/desk"),
    *_picks("", "table", "Scopia/wooden_office_pear_table", "BlendSwap-CC-BY/table", "KatorLegaz/folding-table"),
    *_picks("", "cabinet", "KatorLegaz/filing-cabinet", "Scopia/office_box", "BlendSwap-CC-BY/bookcase",
            "BlendSwap-CC-0/verticalShelves"),
    *_picks("", "sofa", "Scopia/clear_sofa", "KatorLegaz/mid-century-sofa"),
    *_picks("", "water_cooler", "Scopia/water_cooler"),
    *_picks("", "whiteboard", "BlendSwap-CC-0/whiteBoard"),
)

# Poster pictures (photographs): (id, title, catalog, path in the archive, creator). Each makes one poster model
# (the jar's picture frame, eTeks) and one "poster" texture.
POSTER_PICTURES: tuple[tuple[str, str, str, str, str], ...] = (
    ("chambord", "Chateau de Chambord", "Scopia", "scopia/frame1/chambord.jpg", "Scopia & eTeks"),
    ("hoian", "Hoi An street", "Scopia", "scopia/frame2/HoiAn.jpg", "Scopia & eTeks"),
    ("fishes", "Tropical fishes", "Scopia", "scopia/aquarium/fishes.jpg", "Scopia"),
    ("cloudy", "Cloudy sky", JAR, JAR_TEXTURES + "cloudy.jpg", "eTeks"),
    ("very-cloudy", "Very cloudy sky", JAR, JAR_TEXTURES + "veryCloudy.jpg", "eTeks"),
    ("rug", "Oriental rug", "KatorLegaz", "katorlegaz/oriental-rug/rug.jpg", "Kator Legaz"),
)

# Role textures from the jar (eTeks' photographs), office-like ones; the ceiling is derived from roughcast.
ROLE_TEXTURES: dict[str, tuple[str, ...]] = {
    "floor": ("woodenFloor", "greyTile", "beigeTile", "darkBlueTile", "oldWoodenFloor", "lightBlueTile"),
    "wall": ("roughcast", "stone3Wall", "smallWhiteBricks", "marbleWall", "wallBeigeTile"),
}
CEILINGS = (("plaster", 0.0), ("suspended tiles", 0.6))  # (name, grid pitch in metres or 0 for none)


def asset_root() -> Path:
    """`$SITELOC_ASSETS`, else ~/.cache/siteloc/assets-v1: the conversion cache and the jar's extracted files."""
    return env_path("SITELOC_ASSETS") or Path.home() / ".cache" / "siteloc" / "assets-v1"


def default_furniture_dir() -> Path:
    return env_path("SITELOC_SH3D_FURNITURE") or FURNITURE_DIR


def default_jar_source() -> Path:
    """The jar's extracted resources (from install_assets), else an installed sweethome3d's jar."""
    explicit = env_path("SITELOC_SH3D_JAR")
    if explicit:
        return explicit
    extracted = asset_root() / JAR_DIRNAME
    return SYSTEM_JAR if not (extracted / "SOURCE.json").is_file() and SYSTEM_JAR.is_file() else extracted


def _archives(furniture_dir: Path, jar: Path) -> dict[str, Archive]:
    out = {name: Archive(name, FURNITURE_PACKAGE, furniture_dir / f"{name}.sh3f") for name in CATALOG_LICENSES
           if name != JAR}
    out[JAR] = Archive(JAR, JAR_PACKAGE, jar)
    return out


class _Loader:
    """One load: archives, cache, what was missing, counters."""

    def __init__(self, cache: ConversionCache, archives: dict[str, Archive], allow_fallback: bool) -> None:
        self.cache, self.archives, self.allow_fallback = cache, archives, allow_fallback
        self.missing: list[str] = []
        self.stats = {"converted": 0, "from_cache": 0, "skipped": 0}
        self._entries: dict[str, dict[str, obj_catalog.CatalogEntry]] = {}
        self._textures_catalog: dict[str, dict[str, str]] | None = None

    def problem(self, message: str) -> None:
        if not self.allow_fallback:
            raise AssetsUnavailableError(f"{message} ({INSTALL_HINT})")
        if message not in self.missing:
            self.missing.append(message)

    def archive(self, name: str) -> tuple[Archive, str] | tuple[None, None]:
        """The archive and its sha256, or (None, None) after noting why it cannot be used."""
        archive = self.archives[name]
        what = "the Sweet Home 3D jar's resources" if name == JAR else f"{name}.sh3f"
        if not archive.exists():
            self.problem(f"{what} not found at {archive.path}")
            return None, None
        try:
            return archive, self.cache.archive_sha256(archive)
        except OSError as exc:
            self.problem(f"{what} unreadable: {exc}")
            return None, None

    def entry(self, archive: Archive, folder: str) -> obj_catalog.CatalogEntry:
        if archive.name not in self._entries:
            props = JAR_FURNITURE_CATALOG if archive.name == JAR else "PluginFurnitureCatalog.properties"
            entries = obj_catalog.read_catalog(archive.read(props).decode("latin-1"), archive.name)
            self._entries[archive.name] = {e.folder: e for e in entries}
        return self._entries[archive.name][folder]

    def convert(self, archive: Archive, entry: obj_catalog.CatalogEntry) -> tuple[list, dict[str, str]]:
        files: dict[str, str] = {}

        def read(member: str) -> bytes:
            data = archive.read(member)
            files[member] = hashlib.sha256(data).hexdigest()
            return data

        parts, _ = obj_catalog.convert_entry(entry, read, max_triangles=MAX_TRIANGLES, max_texture_px=MODEL_TEXTURE_PX)
        return parts, files

    def model(self, pick: Pick) -> Model | None:
        archive, sha = self.archive(pick.catalog)
        if archive is None or sha is None:
            return None
        key = f"{pick.catalog}/{pick.folder}"
        cached = self.cache.model(key, sha)
        if cached is not None:
            self.stats["from_cache"] += 1
            return cached
        if self.cache.skipped(key, sha):
            self.stats["skipped"] += 1
            return None
        try:
            entry = self.entry(archive, pick.folder)
            parts, files = self.convert(archive, entry)
        except obj_catalog.TooManyTriangles as exc:
            self.cache.store_skip(key, sha, str(exc))
            self.stats["skipped"] += 1
            return None
        except Exception as exc:  # noqa: BLE001 - a broken model must not break the site: fall back, say why
            self.problem(f"{key}: {type(exc).__name__}: {exc}")
            return None
        model = Model(
            key=key, cls=pick.cls, name=entry.name, creator=entry.creator or archive.name,
            license=CATALOG_LICENSES[pick.catalog], source=archive.describe(entry.model_path),
            size=(entry.width_cm / 100, entry.depth_cm / 100, entry.height_cm / 100),
            parts=tuple(_mesh_part(p) for p in parts), procedural=False, kind=pick.kind,
            elevation=entry.elevation_cm / 100, wall_span_y=_wall_span(entry),
        )
        self.cache.store_model(model, sha, files)
        self.stats["converted"] += 1
        return model

    # -- textures

    def texture_catalog(self, jar: Archive) -> dict[str, dict[str, str]]:
        """DefaultTexturesCatalog by image path: name, width/height (cm), creator."""
        if self._textures_catalog is None:
            props = obj_catalog.parse_java_properties(jar.read(JAR_TEXTURE_CATALOG).decode("latin-1"))
            by_image: dict[str, dict[str, str]] = {}
            for key, value in props.items():
                if key.startswith("image#"):
                    n = key.split("#", 1)[1]
                    by_image[value.lstrip("/")] = {k: props.get(f"{k}#{n}", "") for k in ("name", "width", "height",
                                                                                        "creator")}
            self._textures_catalog = by_image
        return self._textures_catalog

    def jar_texture(self, role: str, name: str) -> tuple[TextureInfo, np.ndarray] | None:
        jar, sha = self.archive(JAR)
        if jar is None or sha is None:
            return None
        key, member = f"{role}/{name}", f"{JAR_TEXTURES}{name}.jpg"
        cached = self.cache.texture(key, sha)
        if cached is not None:
            return cached
        try:
            meta = self.texture_catalog(jar).get(member, {})
            image = obj_catalog.load_image(jar.read(member), ROLE_TEXTURE_PX)
            tile = (float(meta["width"]) / 100, float(meta["height"]) / 100) if meta.get("width") else None
        except Exception as exc:  # noqa: BLE001
            self.problem(f"texture {key}: {type(exc).__name__}: {exc}")
            return None
        info = TextureInfo(role=role, name=meta.get("name") or name, creator=meta.get("creator") or "eTeks",
                           license=CC_BY, source=jar.describe(member), tile_size_m=tile)
        self.cache.store_texture(key, info, image, sha)
        return info, image

    def picture(self, pic: tuple[str, str, str, str, str]) -> tuple[TextureInfo, np.ndarray, str] | None:
        pid, title, catalog, member, creator = pic
        archive, sha = self.archive(catalog)
        if archive is None or sha is None:
            return None
        cached = self.cache.texture(f"poster/{pid}", sha)
        if cached is not None:
            return (*cached, sha)
        try:
            image = _crop_aspect(obj_catalog.load_image(archive.read(member), ROLE_TEXTURE_PX), 0.6, 1.6)
        except Exception as exc:  # noqa: BLE001
            self.problem(f"poster picture {pid}: {type(exc).__name__}: {exc}")
            return None
        info = TextureInfo(role="poster", name=title, creator=creator, license=CATALOG_LICENSES[catalog],
                           source=archive.describe(member), tile_size_m=None)
        self.cache.store_texture(f"poster/{pid}", info, image, sha)
        return info, image, sha

    def poster(self, pid: str, info: TextureInfo, image: np.ndarray, picture_sha: str) -> Model | None:
        """The jar's picture frame (eTeks) sized to the picture (long side 0.8 m), the picture on its front."""
        jar, jar_sha = self.archive(JAR)
        if jar is None or jar_sha is None:
            return None
        key = f"{JAR}/frame+{pid}"
        sha = combined_sha(jar_sha, picture_sha)
        cached = self.cache.model(key, sha)
        if cached is not None:
            self.stats["from_cache"] += 1
            return cached
        try:
            frame = self.entry(jar, "frame")
            aspect = image.shape[1] / image.shape[0]
            height = 80.0 if aspect <= 1 else 80.0 / aspect
            entry = dataclasses.replace(frame, width_cm=height * aspect, height_cm=height)
            parts, files = self.convert(jar, entry)
        except Exception as exc:  # noqa: BLE001
            self.problem(f"{key}: {type(exc).__name__}: {exc}")
            return None
        mesh_parts = []
        for p in parts:
            if p.material == "Mirror":
                continue  # the frame doubles as a mirror in Sweet Home 3D; a poster has only the picture
            if p.material == "Picture":
                p = dataclasses.replace(p, texture=image, colour=(1.0, 1.0, 1.0))
            mesh_parts.append(_mesh_part(p, role="picture" if p.material == "Picture" else ""))
        model = Model(
            key=key, cls="poster", name=f"Poster: {info.name}", creator=f"{frame.creator} (frame), {info.creator}",
            license=_combine_licenses(CC_BY, info.license), source=f"{jar.describe(frame.model_path)} + {info.source}",
            size=(entry.width_cm / 100, entry.depth_cm / 100, entry.height_cm / 100), parts=tuple(mesh_parts),
            procedural=False, kind="poster", elevation=frame.elevation_cm / 100,
        )
        self.cache.store_model(model, sha, files)
        self.stats["converted"] += 1
        return model


def _mesh_part(p: obj_catalog.PartArrays, role: str = "") -> MeshPart:
    # With a texture, the colour is white: the renderer multiplies texture by colour, and these MTLs' Kd next to
    # a map_Kd (often Blender's 0.64 grey) is not meant to darken the photograph.
    colour = (1.0, 1.0, 1.0) if p.texture is not None else p.colour
    return MeshPart(positions=p.positions, normals=p.normals, uvs=p.uvs, texture=p.texture, colour=colour,
                    opacity=p.opacity, role=role)


def _wall_span(entry: obj_catalog.CatalogEntry) -> tuple[float, float] | None:
    """y interval of the wall in the MODEL frame: the catalog measures thickness and distance from the back (+y)."""
    if not entry.door_or_window:
        return None
    depth = entry.depth_cm / 100
    thickness = (entry.wall_thickness_cm if entry.wall_thickness_cm is not None else entry.depth_cm) / 100
    distance = (entry.wall_distance_cm or 0.0) / 100
    return (depth / 2 - distance - thickness, depth / 2 - distance)


def _crop_aspect(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Centre-crop to an aspect ratio (width / height) within [lo, hi]: panoramas make poor posters."""
    h, w = image.shape[:2]
    if w / h > hi:
        nw = int(round(h * hi))
        return image[:, (w - nw) // 2 : (w - nw) // 2 + nw].copy()
    if w / h < lo:
        nh = int(round(w / lo))
        return image[(h - nh) // 2 : (h - nh) // 2 + nh].copy()
    return image


def _combine_licenses(*licenses: str) -> str:
    """An SPDX AND-expression of the distinct licences (a poster: the frame's and the picture's)."""
    return " AND ".join(sorted(set(licenses)))


def derive_ceiling(plaster: np.ndarray, tile_m: float, pitch_m: float) -> np.ndarray:
    """A ceiling from a plaster photograph: lightened towards white, optionally with a suspended-ceiling grid.

    The grid texture covers one grid cell (pitch_m), tiling the plaster photo inside it."""
    base = plaster.astype(np.float32)
    if pitch_m > 0:
        reps = max(1, int(round(pitch_m / tile_m)))
        base = np.tile(base, (reps, reps, 1))
    light = 0.35 * base + 0.65 * 245.0
    if pitch_m > 0:
        n = max(2, base.shape[0] // 120)
        light[:n], light[:, :n] = 150.0, 150.0
    out = np.clip(light, 0, 255).astype(np.uint8)
    if max(out.shape[:2]) > ROLE_TEXTURE_PX:
        from PIL import Image

        img = Image.fromarray(out)
        img.thumbnail((ROLE_TEXTURE_PX, ROLE_TEXTURE_PX), Image.Resampling.LANCZOS)
        out = np.asarray(img, dtype=np.uint8).copy()
    return out


def load_assets(
    classes: Iterable[str] = CLASSES,
    *,
    cache_dir: Path | None = None,
    allow_fallback: bool = True,
    furniture: bool = True,
    furniture_dir: Path | None = None,
    jar: Path | None = None,
) -> AssetLibrary:
    """Models for `classes` (+ desks, tables, cabinets... under FURNITURE), textures by role, attribution.

    cache_dir: conversion cache (default `asset_root()`). furniture_dir / jar: the sources (defaults:
    /usr/share/sweethome3d/furniture, `asset_root()/sweethome3d-jar`; env SITELOC_SH3D_FURNITURE /
    SITELOC_SH3D_JAR). allow_fallback=False raises AssetsUnavailableError instead of generating stand-ins.
    """
    t0 = time.perf_counter()
    classes = tuple(classes)
    unknown = sorted(set(classes) - set(CLASSES))
    if unknown:
        raise ValueError(f"unknown classes {unknown}; known: {list(CLASSES)}")
    settings = {"max_triangles": MAX_TRIANGLES, "model_texture_px": MODEL_TEXTURE_PX,
                "role_texture_px": ROLE_TEXTURE_PX, "converter": CONVERTER_VERSION}
    cache = ConversionCache(Path(cache_dir) if cache_dir else asset_root(), settings)
    loader = _Loader(cache, _archives(furniture_dir or default_furniture_dir(), jar or default_jar_source()),
                     allow_fallback)
    wanted = set(classes) | ({""} if furniture else set())
    models: dict[str, list[Model]] = {cls: [] for cls in classes}
    if furniture:
        models[FURNITURE] = []
    for pick in MODEL_PICKS:
        if pick.cls in wanted:
            model = loader.model(pick)
            if model is not None:
                models[pick.cls or FURNITURE].append(model)

    pictures = [(pic[0], *found) for pic in POSTER_PICTURES if (found := loader.picture(pic)) is not None]
    if "poster" in classes:
        for pid, info, image, sha in pictures:
            model = loader.poster(pid, info, image, sha)
            if model is not None:
                models["poster"].append(model)

    textures: dict[str, list[np.ndarray]] = {role: [] for role in ("floor", "wall", "ceiling", "poster")}
    infos: dict[str, list[TextureInfo]] = {role: [] for role in textures}
    for role, names in ROLE_TEXTURES.items():
        for name in names:
            found = loader.jar_texture(role, name)
            if found is not None:
                infos[role].append(found[0])
                textures[role].append(found[1])
    plaster = loader.jar_texture("wall", "roughcast") if infos["wall"] else None
    if plaster is not None:
        tile = (plaster[0].tile_size_m or (0.2, 0.2))[0]
        for name, pitch in CEILINGS:
            infos["ceiling"].append(dataclasses.replace(
                plaster[0], role="ceiling", name=f"{name} (from {plaster[0].name}, lightened)",
                tile_size_m=(pitch, pitch) if pitch else plaster[0].tile_size_m))
            textures["ceiling"].append(derive_ceiling(plaster[1], tile, pitch))
    for _, info, image, _ in pictures:
        infos["poster"].append(info)
        textures["poster"].append(image)

    generated = _fill_with_procedural(models, textures, infos, classes, furniture, loader)
    cache.save()
    if loader.missing:
        used = f"procedural stand-ins used for {', '.join(generated)}" if generated else "no stand-ins needed"
        warnings.warn(f"siteloc assets: {used}; missing: {'; '.join(loader.missing)}. For real assets: {INSTALL_HINT}.",
                      AssetFallbackWarning, stacklevel=2)
    library = AssetLibrary(models=models, textures=textures, texture_info=infos,
                           attribution=_attribution(models, infos), procedural=bool(generated),
                           missing=list(loader.missing),
                           stats={**loader.stats, "seconds": round(time.perf_counter() - t0, 3)})
    return library


def _fill_with_procedural(models, textures, infos, classes, furniture, loader: _Loader) -> list[str]:
    """Stand-ins for every class / furniture kind / texture role left empty; returns what was generated."""
    generated = []
    pictures = textures["poster"] or None
    for cls in classes:
        if not models[cls]:
            loader.problem(f"no usable real model for class {cls}")
            models[cls] = procedural_assets.models_for(cls, pictures or [])
            generated.append(cls)
            if cls == "poster" and pictures:  # generated frames around real photographs: credit the photographs
                models[cls] = [dataclasses.replace(m, creator=f"{m.creator} (frame), {info.creator}",
                                                   license=_combine_licenses(m.license, info.license))
                               for m, info in zip(models[cls], infos["poster"], strict=True)]
    if furniture:
        have = {m.kind for m in models[FURNITURE]}
        for stand_in in procedural_assets.models_for("", []):
            if stand_in.kind not in have:
                models[FURNITURE].append(stand_in)
                if f"furniture:{stand_in.kind}" not in generated:
                    loader.problem(f"no usable real model for furniture kind {stand_in.kind}")
                    generated.append(f"furniture:{stand_in.kind}")
    fallback = procedural_assets.role_textures()
    for role in textures:
        if not textures[role]:
            loader.problem(f"no photographic {role} texture")
            for info, image in fallback[role]:
                infos[role].append(info)
                textures[role].append(image)
            generated.append(f"{role} textures")
    return generated


def _attribution(models: dict[str, list[Model]], infos: dict[str, list[TextureInfo]]) -> list[dict[str, str]]:
    rows = []
    for cls, items in models.items():
        for m in items:
            rows.append({"type": "model", "key": m.key, "name": m.name, "used_as": m.kind or cls,
                         "creator": m.creator, "license": m.license, "source": m.source,
                         "procedural": str(m.procedural).lower()})
    for role, items in infos.items():
        for t in items:
            rows.append({"type": "texture", "key": f"{role}/{t.name}", "name": t.name, "used_as": role,
                         "creator": t.creator, "license": t.license, "source": t.source,
                         "procedural": str(t.procedural).lower()})
    return rows


def describe(library: AssetLibrary) -> str:
    """One line per class: how many models and their triangle counts (for logs and install_assets)."""
    out = []
    for cls, items in library.models.items():
        tris = ", ".join(str(m.n_triangles) for m in items)
        out.append(f"{cls:18s} {len(items):2d} model(s){' (procedural)' if any(m.procedural for m in items) else ''}"
                   f"  triangles: {tris}")
    for role, items in library.textures.items():
        out.append(f"texture {role:10s} {len(items):2d}")
    return "\n".join(out)

