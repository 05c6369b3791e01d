"""Sweet Home 3D catalogs and their OBJ/MTL models, read straight from the Debian archives (no Java).

Why a small parser of our own rather than trimesh: measured on these files (trimesh 5.2, `trimesh.load(...,
file_type="obj", resolver=...)`), trimesh loads the materials only with a dict-like resolver, drops the
texture coordinates of textured parts when some faces of the file have no `vt` (the emergency sign, the
extinguisher label), ignores the MTL opacity `d` (window glass), and keeps every vertex of the file in every
part. The files here are plain Blender/Sweet Home 3D exports (v/vt/vn/f/usemtl/s/g/o, polygons, negative
indices), so the ~150 lines below read them exactly, into the non-indexed triangle soup the renderer wants,
at ~0.1 s per 10k triangles. Normals: most of these OBJs carry none, so they are generated from the final
(scaled) geometry, smoothed inside each OBJ smoothing group with a 45-degree crease angle.

Frames. Sweet Home 3D model frame ("SH3D"): y up, the model's front faces +z, width along x; the catalog's
`modelRotation` (row-major 3x3, applied as v' = R v) turns a raw OBJ into that frame, then the bounding box
is scaled to width x height x depth (centimetres) and centred. Our model frame ("MODEL", see
`asset_types`): metres, z up, front faces -y, width along x, depth along y, origin at the centre of the
footprint on the floor. MODEL = (x_sh3d, -z_sh3d, y_sh3d), a proper rotation (det +1), so the winding of
the triangles (counter-clockwise seen from outside) is kept.
"""

from __future__ import annotations

import dataclasses
import io
import re
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import PurePosixPath

import numpy as np
from PIL import Image

CREASE_COS = float(np.cos(np.deg2rad(45.0)))

# SH3D frame (y up, front +z) -> MODEL frame (z up, front -y): rows give MODEL axes in SH3D coordinates.
SH3D_TO_MODEL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class TooManyTriangles(ValueError):
    """The model is over the triangle budget: the caller skips it for another candidate."""


# ---------------------------------------------------------------------------------------------- catalogs


def parse_java_properties(text: str) -> dict[str, str]:
    """Java `.properties` (the catalog format): comments, `key=value` / `key: value`, backslash line
    continuations, `\\uXXXX` and `\\=`-style escapes. Decode the bytes as latin-1 first (Java's rule)."""
    out: dict[str, str] = {}
    pending = ""
    for raw in text.splitlines():
        line = raw.lstrip()
        if not pending and (not line or line[0] in "#!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:  # odd number of backslashes: continuation
            pending += line[:-1]
            continue
        line, pending = pending + line, ""
        match = re.match(r"((?:[^\\=:\s]|\\.)+)\s*[=:\s]?\s*(.*)$", line)
        if match:
            out[_unescape(match.group(1))] = _unescape(match.group(2))
    return out


def _unescape(value: str) -> str:
    def repl(match: re.Match[str]) -> str:
        token = match.group(1)
        if token.startswith("u"):
            return chr(int(token[1:], 16))
        return {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}.get(token, token)

    return re.sub(r"\\(u[0-9a-fA-F]{4}|.)", repl, value)


@dataclass(frozen=True)
class CatalogEntry:
    """One piece of furniture of a Sweet Home 3D catalog (sizes in centimetres, as the catalog gives them)."""

    catalog: str  # "Scopia", "BlendSwap-CC-0", ..., or "sweethome3d.jar"
    index: int  # the N of `name#N`
    name: str
    category: str
    creator: str
    model_path: str  # path of the OBJ inside the archive, no leading slash
    width_cm: float
    depth_cm: float
    height_cm: float
    model_rotation: tuple[float, ...] | None  # 9 values, row-major, in the SH3D frame
    door_or_window: bool
    elevation_cm: float
    wall_thickness_cm: float | None
    wall_distance_cm: float | None

    @property
    def folder(self) -> str:
        """Model folder name ("fireExtinguisher" for blendswap-cc-0/fireExtinguisher/x.obj): the stable id."""
        parent = PurePosixPath(self.model_path).parent.name
        return parent if parent not in ("", "resources") else PurePosixPath(self.model_path).stem


def read_catalog(props_text: str, catalog: str) -> list[CatalogEntry]:
    """Entries of a `PluginFurnitureCatalog.properties` / `DefaultFurnitureCatalog.properties` text."""
    props = parse_java_properties(props_text)
    indices = sorted({int(k.split("#", 1)[1]) for k in props if k.startswith("model#")})
    entries = []
    for n in indices:

        def get(key: str, default: str = "", n: int = n) -> str:
            return props.get(f"{key}#{n}", default).strip()

        def num(key: str, n: int = n) -> float | None:
            value = props.get(f"{key}#{n}")
            try:
                return float(value) if value is not None else None
            except ValueError:
                return None

        rotation = tuple(float(v) for v in get("modelRotation").split()) or None
        if rotation is not None and len(rotation) != 9:
            rotation = None
        entries.append(
            CatalogEntry(
                catalog=catalog,
                index=n,
                name=get("name"),
                category=get("category"),
                creator=get("creator"),
                model_path=get("model").lstrip("/"),
                width_cm=num("width") or 0.0,
                depth_cm=num("depth") or 0.0,
                height_cm=num("height") or 0.0,
                model_rotation=rotation,
                door_or_window=get("doorOrWindow").lower() == "true",
                elevation_cm=num("elevation") or 0.0,
                wall_thickness_cm=num("doorOrWindowWallThickness"),
                wall_distance_cm=num("doorOrWindowWallDistance"),
            )
        )
    return entries


# ---------------------------------------------------------------------------------------------- OBJ / MTL


@dataclass(frozen=True)
class Material:
    name: str
    diffuse: tuple[float, float, float] = (0.8, 0.8, 0.8)
    opacity: float = 1.0
    texture: str | None = None  # file name as written after map_Kd, relative to the MTL


# Java3D's built-in material library (com.sun.j3d.loaders.objectfile.DefaultMaterials): the jar's own OBJs say
# `usemtl white` with no mtllib and rely on it. Diffuse colours of the names those models use (and a few more).
JAVA3D_DEFAULT_DIFFUSE: dict[str, tuple[float, float, float]] = {
    "white": (1.0, 1.0, 1.0), "black": (0.002, 0.002, 0.002), "flblack": (0.0041, 0.0041, 0.0041),
    "grey": (0.1837, 0.1837, 0.1837), "flgrey": (0.5, 0.5, 0.5), "flltgrey": (0.8245, 0.8245, 0.8245),
    "ltgrey": (0.3837, 0.3837, 0.3837), "fldkgrey": (0.0939, 0.0939, 0.0939), "silver": (0.6163, 0.6163, 0.6163),
    "yellowbrt": (1.0, 0.7837, 0.0), "amber": (0.5755, 0.2678, 0.0), "flbrown": (0.1102, 0.012, 0.0013),
    "yellow_green": (0.1875, 0.4082, 0.0017), "archwhite": (0.9959, 0.9959, 0.9959),
    "archwhite2": (0.8408, 0.8408, 0.8408), "lighttan": (0.702, 0.421, 0.2206), "tan": (0.6612, 0.5221, 0.2186),
    "brass": (0.4776, 0.1959, 0.0), "glass": (0.4873, 0.4919, 0.5306), "redwood": (0.2571, 0.033, 0.0),
}
WINDOW_PANE_PREFIX = "sweethome3d_window_pane"  # Sweet Home 3D draws groups so named as glass
PANE_OPACITY = 0.5


def parse_mtl(text: str) -> dict[str, Material]:
    """`newmtl`, `Kd`, `d` / `Tr` (opacity), `map_Kd` (options such as `-s u v w` are skipped)."""
    materials: dict[str, Material] = {}
    current: dict | None = None

    def flush() -> None:
        if current is not None:
            materials[current["name"]] = Material(**current)

    for raw in text.splitlines():
        parts = raw.strip().split(None, 1)
        if not parts or parts[0].startswith("#"):
            continue
        key, rest = parts[0], (parts[1].strip() if len(parts) > 1 else "")
        if key == "newmtl":
            flush()
            current = {"name": rest}
        elif current is None:
            continue
        elif key == "Kd":
            values = [float(v) for v in rest.split()[:3]]
            if len(values) == 3:
                current["diffuse"] = tuple(float(np.clip(v, 0.0, 1.0)) for v in values)
        elif key == "d":
            current["opacity"] = float(np.clip(float(rest.split()[-1]), 0.0, 1.0))
        elif key == "Tr" and "opacity" not in current:
            opacity = 1.0 - float(rest.split()[-1])
            current["opacity"] = opacity if opacity > 0.05 else 1.0  # some exporters write Tr as d
        elif key == "map_Kd":
            current["texture"] = _strip_map_options(rest)
    flush()
    return materials


_MAP_OPTION_ARGS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
                    "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1}


def _strip_map_options(rest: str) -> str:
    tokens = rest.split(" ")
    i = 0
    while i < len(tokens) and tokens[i] in _MAP_OPTION_ARGS:
        i += 1 + _MAP_OPTION_ARGS[tokens[i]]
    return " ".join(tokens[i:]).strip().replace("\\", "/")


@dataclass
class ObjMesh:
    """An OBJ as triangle corners: indices into positions/uvs/normals (-1 = absent), a material and a
    smoothing group per triangle."""

    positions: np.ndarray  # (V,3) float64, file frame
    uvs: np.ndarray  # (T,2) float64, OBJ convention (v up)
    normals: np.ndarray  # (N,3) float64
    corner_v: np.ndarray  # (F*3,) int64
    corner_t: np.ndarray
    corner_n: np.ndarray
    tri_material: np.ndarray  # (F,) int64 index into material_names
    tri_smooth: np.ndarray  # (F,) int64, 0 = flat
    tri_pane: np.ndarray  # (F,) bool: in a `sweethome3d_window_pane*` group
    material_names: list[str]
    mtllibs: list[str]


def _floats(lines: list[str], width: int) -> np.ndarray:
    if not lines:
        return np.zeros((0, width))
    rows = [line.split()[1 : 1 + width] for line in lines]
    rows = [r + ["0"] * (width - len(r)) for r in rows]
    return np.asarray(rows, dtype=np.float64).reshape(-1, width)


def parse_obj(text: str) -> ObjMesh:
    """Read v/vt/vn/f/usemtl/s/mtllib; polygons are fan-triangulated; negative indices are resolved."""
    v_lines: list[str] = []
    vt_lines: list[str] = []
    vn_lines: list[str] = []
    cv: list[int] = []
    ct: list[int] = []
    cn: list[int] = []
    tri_mat: list[int] = []
    tri_sg: list[int] = []
    tri_pane: list[bool] = []
    pane = False
    materials: dict[str, int] = {}
    mtllibs: list[str] = []
    mat, sg, saw_s = -1, 1, False
    for line in text.splitlines():
        if not line or line[0] == "#":
            continue
        head = line[:2]
        if head == "v ":
            v_lines.append(line)
        elif head == "vt":
            vt_lines.append(line)
        elif head == "vn":
            vn_lines.append(line)
        elif head == "f ":
            nv, nt, nn = len(v_lines), len(vt_lines), len(vn_lines)
            corners = []
            for tok in line.split()[1:]:
                parts = tok.split("/")
                vi = int(parts[0])
                ti = int(parts[1]) if len(parts) > 1 and parts[1] else 0
                ni = int(parts[2]) if len(parts) > 2 and parts[2] else 0
                corners.append(
                    (vi - 1 if vi > 0 else nv + vi, (ti - 1 if ti > 0 else nt + ti) if ti else -1,
                     (ni - 1 if ni > 0 else nn + ni) if ni else -1)
                )
            for k in range(1, len(corners) - 1):
                for c in (corners[0], corners[k], corners[k + 1]):
                    cv.append(c[0])
                    ct.append(c[1])
                    cn.append(c[2])
                tri_mat.append(mat)
                tri_sg.append(sg)
                tri_pane.append(pane)
        elif head == "g " or head == "o ":
            pane = line[2:].strip().startswith(WINDOW_PANE_PREFIX)
        elif line.startswith("usemtl"):
            name = line[6:].strip()
            mat = materials.setdefault(name, len(materials))
        elif head == "s " or line == "s":
            saw_s = True
            value = line[1:].strip().lower()
            sg = 0 if value in ("off", "0", "") else (int(value) if value.isdigit() else 1)
        elif line.startswith("mtllib"):
            mtllibs.extend(line[6:].split())
    if not saw_s:
        tri_sg = [1] * len(tri_sg)  # no smoothing statements at all: smooth everything (crease-limited)
    names = [""] * len(materials)
    for name, i in materials.items():
        names[i] = name
    if any(m < 0 for m in tri_mat):
        names.append("")  # faces before any usemtl
        tri_mat = [m if m >= 0 else len(names) - 1 for m in tri_mat]
    return ObjMesh(
        positions=_floats(v_lines, 3),
        uvs=_floats(vt_lines, 2),
        normals=_floats(vn_lines, 3),
        corner_v=np.asarray(cv, dtype=np.int64),
        corner_t=np.asarray(ct, dtype=np.int64),
        corner_n=np.asarray(cn, dtype=np.int64),
        tri_material=np.asarray(tri_mat, dtype=np.int64),
        tri_smooth=np.asarray(tri_sg, dtype=np.int64),
        tri_pane=np.asarray(tri_pane, dtype=bool),
        material_names=names,
        mtllibs=mtllibs,
    )


def smooth_normals(corners: np.ndarray, corner_v: np.ndarray, tri_smooth: np.ndarray) -> np.ndarray:
    """Per-corner normals for a triangle soup `corners` (F*3,3): area-weighted mean of the face normals
    sharing an OBJ vertex inside a smoothing group, replaced by the face normal beyond the crease angle
    (so boxes stay boxes) and for flat faces (group 0)."""
    tri = corners.reshape(-1, 3, 3)
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(face, axis=1, keepdims=True)
    face_unit = face / np.maximum(length, 1e-30)
    face_c = np.repeat(face_unit, 3, axis=0)
    sg_c = np.repeat(tri_smooth, 3)
    key = corner_v * (int(tri_smooth.max(initial=0)) + 1) + sg_c
    _, group = np.unique(key, return_inverse=True)
    weighted = np.repeat(face, 3, axis=0)
    summed = np.stack([np.bincount(group, weighted[:, k], minlength=group.max(initial=-1) + 1) for k in range(3)], 1)
    mean = summed[group]
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-30)
    smooth = (sg_c > 0) & (np.einsum("ij,ij->i", mean, face_c) >= CREASE_COS)
    return np.where(smooth[:, None], mean, face_c)


# ------------------------------------------------------------------------------------ conversion to MODEL


@dataclass
class PartArrays:
    """One material's triangles in the MODEL frame; `texture` is an (H,W,3) uint8 image, row 0 = top."""

    positions: np.ndarray  # (N,3) float32
    normals: np.ndarray  # (N,3) float32, unit
    uvs: np.ndarray  # (N,2) float32, OBJ/OpenGL convention: (0, 0) = bottom-left of the image, v up
    texture: np.ndarray | None
    colour: tuple[float, float, float]
    opacity: float
    material: str


def load_image(data: bytes, max_px: int) -> np.ndarray:
    """Decode to RGB uint8 (alpha composited over mid grey: these textures are used opaque), downscaled so
    the longer side is <= max_px (rendering on llvmpipe: small textures are cheaper to sample)."""
    with Image.open(io.BytesIO(data)) as img:
        img.load()
        if img.mode in ("RGBA", "LA", "P"):
            rgba = img.convert("RGBA")
            base = Image.new("RGBA", rgba.size, (128, 128, 128, 255))
            img = Image.alpha_composite(base, rgba).convert("RGB")
        else:
            img = img.convert("RGB")
        if max(img.size) > max_px:
            img.thumbnail((max_px, max_px), Image.Resampling.LANCZOS)
        return np.asarray(img, dtype=np.uint8).copy()


def convert_entry(
    entry: CatalogEntry,
    read: Callable[[str], bytes],
    *,
    max_triangles: int,
    max_texture_px: int,
) -> tuple[list[PartArrays], int]:
    """Parse `entry`'s OBJ (files fetched with `read(path_in_archive)`), apply its modelRotation, go to the
    MODEL frame and scale to the catalog size. Returns the parts and the triangle count; raises ValueError
    when the model has more than `max_triangles` (the caller picks another) or no usable geometry."""
    obj_dir = PurePosixPath(entry.model_path).parent
    mesh = parse_obj(read(entry.model_path).decode("latin-1"))
    n_tri = len(mesh.tri_material)
    if n_tri == 0:
        raise ValueError(f"{entry.model_path}: no faces")
    if n_tri > max_triangles:
        raise TooManyTriangles(f"{entry.model_path}: {n_tri} triangles > {max_triangles}")
    materials: dict[str, Material] = {}
    for lib in mesh.mtllibs:
        try:
            materials.update(parse_mtl(read(str(obj_dir / lib)).decode("latin-1")))
        except KeyError:
            continue

    rotation = np.eye(3) if entry.model_rotation is None else np.asarray(entry.model_rotation).reshape(3, 3)
    linear = SH3D_TO_MODEL @ rotation  # file frame -> MODEL orientation (before scaling)
    pts = mesh.positions @ linear.T
    used = pts[mesh.corner_v]
    lo, hi = used.min(axis=0), used.max(axis=0)
    extent = np.maximum(hi - lo, 1e-9)
    target = np.array([entry.width_cm, entry.depth_cm, entry.height_cm]) / 100.0
    scale = np.where(target > 0, target / extent, 1.0)
    offset = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    corners = (used + offset) * scale
    mirrored = np.linalg.det(linear) < 0
    if mirrored:  # keep counter-clockwise winding
        order = np.arange(len(corners)).reshape(-1, 3)[:, [0, 2, 1]].ravel()
        corners, perm = corners[order], order
    else:
        perm = np.arange(len(corners))
    corner_v = mesh.corner_v[perm]
    corner_t = mesh.corner_t[perm]
    corner_n = mesh.corner_n[perm]

    normals = smooth_normals(corners, corner_v, mesh.tri_smooth)
    has_n = corner_n >= 0
    if has_n.all() and len(mesh.normals):
        # Normals from the file: n' = M^-T n for the whole linear map M = diag(scale) @ linear.
        inv_t = np.linalg.inv(np.diag(scale) @ linear).T
        given = mesh.normals[corner_n] @ inv_t.T
        given /= np.maximum(np.linalg.norm(given, axis=1, keepdims=True), 1e-30)
        ok = np.isfinite(given).all(axis=1) & (np.linalg.norm(given, axis=1) > 0.5)
        normals = np.where(ok[:, None], given, normals)

    uvs = np.zeros((len(corners), 2))
    has_t = (corner_t >= 0) & (corner_t < len(mesh.uvs))
    uvs[has_t] = mesh.uvs[corner_t[has_t]]  # kept in the OBJ/OpenGL convention (v up), as the renderer wants

    tri = corners.reshape(-1, 3, 3)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep_tri = area2 > 1e-12
    parts: list[PartArrays] = []
    textures: dict[str, np.ndarray | None] = {}
    groups = sorted(set(zip(mesh.tri_material[keep_tri].tolist(), mesh.tri_pane[keep_tri].tolist(), strict=True)))
    for m_index, pane in groups:
        m_name = mesh.material_names[m_index]
        sel = np.repeat(keep_tri & (mesh.tri_material == m_index) & (mesh.tri_pane == pane), 3)
        material = materials.get(m_name) or Material(m_name, JAVA3D_DEFAULT_DIFFUSE.get(m_name, (0.8, 0.8, 0.8)))
        if pane:
            material = dataclasses.replace(material, opacity=min(material.opacity, PANE_OPACITY))
        if material.opacity <= 0.01:
            continue  # invisible helper geometry
        texture = None
        if material.texture:
            if material.texture not in textures:
                textures[material.texture] = _read_texture(read, obj_dir, material.texture, max_texture_px)
            texture = textures[material.texture]
            if texture is not None and not has_t[sel].any():
                texture = None  # a texture without coordinates would paint one texel everywhere
        parts.append(PartArrays(
            positions=corners[sel].astype(np.float32), normals=normals[sel].astype(np.float32),
            uvs=uvs[sel].astype(np.float32), texture=texture, colour=material.diffuse, opacity=material.opacity,
            material=m_name,
        ))
    if not parts:
        raise ValueError(f"{entry.model_path}: no visible geometry")
    return parts, int(keep_tri.sum())


def _read_texture(read: Callable[[str], bytes], obj_dir: PurePosixPath, name: str, max_px: int) -> np.ndarray | None:
    for candidate in (str(obj_dir / name), str(obj_dir / PurePosixPath(name).name)):
        try:
            return load_image(read(candidate), max_px)
        except (KeyError, FileNotFoundError, OSError, ValueError):
            continue
    return None


def zip_reader(archive: zipfile.ZipFile) -> Callable[[str], bytes]:
    """`read(path)` over a zip, falling back to a case-insensitive match (models written on Windows)."""
    lower = {name.lower(): name for name in archive.namelist()}

    def read(path: str) -> bytes:
        path = path.lstrip("/")
        try:
            return archive.read(path)
        except KeyError:
            return archive.read(lower[path.lower()])

    return read
