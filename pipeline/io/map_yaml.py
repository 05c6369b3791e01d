"""ROS map_server maps: a YAML description plus an image (PGM by default).

Semantics follow map_server/nav2_map_server: with `negate: 0` a pixel's occupancy probability is
(255 - value) / 255; occupied above `occupied_thresh`, free below `free_thresh`, unknown between
(mode `trinary`). `origin` is the map-frame pose of the lower-left pixel, so image row 0 is the
top of the map. Inside siteloc the grid is stored bottom-up (row 0 = lowest y), as in
nav_msgs/OccupancyGrid: cell (row, col) covers x in origin_x + [col, col+1) * resolution.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.errors import InputError, Problem
from pipeline.io.atomic import atomic_file, write_text_atomic
from pipeline.io.images import ImageError
from pipeline.io.text_files import read_text

FREE, UNKNOWN, OCCUPIED = 0, -1, 100
_MODES = ("trinary", "scale", "raw")
_REQUIRED = ("image", "resolution", "origin")
_KNOWN = set(_REQUIRED) | {"negate", "occupied_thresh", "free_thresh", "mode"}


@dataclass(frozen=True)
class OccupancyMap:
    """Occupancy grid: int8 cells, -1 unknown, 0 free, 100 occupied (1..99 only in `scale` maps); row 0 = lowest y."""

    grid: np.ndarray
    resolution: float
    origin_x: float = 0.0
    origin_y: float = 0.0
    origin_yaw: float = 0.0

    @property
    def height(self) -> int:
        return int(self.grid.shape[0])

    @property
    def width(self) -> int:
        return int(self.grid.shape[1])

    @property
    def occupied(self) -> np.ndarray:
        return self.grid == OCCUPIED

    @property
    def free(self) -> np.ndarray:
        return self.grid == FREE

    @property
    def unknown(self) -> np.ndarray:
        return self.grid < 0

    def world_to_cell(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) integer cells of map-frame points; may lie outside the grid (see `contains`)."""
        x = np.asarray(x, dtype=np.float64) - self.origin_x
        y = np.asarray(y, dtype=np.float64) - self.origin_y
        if self.origin_yaw:
            c, s = np.cos(-self.origin_yaw), np.sin(-self.origin_yaw)
            x, y = c * x - s * y, s * x + c * y
        col = np.floor(x / self.resolution).astype(np.int64)
        row = np.floor(y / self.resolution).astype(np.int64)
        return row, col

    def cell_to_world(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame centre of cells."""
        u = (np.asarray(col, dtype=np.float64) + 0.5) * self.resolution
        v = (np.asarray(row, dtype=np.float64) + 0.5) * self.resolution
        if self.origin_yaw:
            c, s = np.cos(self.origin_yaw), np.sin(self.origin_yaw)
            u, v = c * u - s * v, s * u + c * v
        return u + self.origin_x, v + self.origin_y

    def contains(self, row, col) -> np.ndarray:
        row, col = np.asarray(row), np.asarray(col)
        return (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)

    def value_at(self, x, y, outside: int = UNKNOWN) -> np.ndarray:
        """Grid value at map-frame points; `outside` where they leave the grid."""
        row, col = self.world_to_cell(x, y)
        inside = self.contains(row, col)
        out = np.full(np.shape(row), outside, dtype=np.int16)
        out[inside] = self.grid[row[inside], col[inside]]
        return out


def _problem(path: Path, message: str, key: str | None = None, fix: str | None = None) -> Problem:
    return Problem(str(path), message, key=key, fix=fix)


def read_map(yaml_path: Path) -> OccupancyMap:
    """Read a map_server YAML + image. Every problem found is reported at once."""
    yaml_path = Path(yaml_path)
    if not yaml_path.is_file():
        raise InputError(
            f"{yaml_path}: map not found", [_problem(yaml_path, "file is missing", fix="add a map_server map.yaml")]
        )
    try:
        meta = yaml.safe_load(read_text(yaml_path, what="map description"))
    except yaml.YAMLError as exc:
        raise InputError(f"{yaml_path}: not valid YAML", [_problem(yaml_path, str(exc))]) from None
    if not isinstance(meta, dict):
        raise InputError(f"{yaml_path}: not a map description", [_problem(yaml_path, "top level must be a mapping")])
    problems: list[Problem] = []
    for key in _REQUIRED:
        if key not in meta:
            problems.append(_problem(yaml_path, "required key is missing", key=key))
    for key in sorted(set(meta) - _KNOWN):
        problems.append(_problem(yaml_path, f"unknown key (known: {', '.join(sorted(_KNOWN))})", key=key))
    res = meta.get("resolution")
    if "resolution" in meta and not (isinstance(res, int | float) and res > 0):
        problems.append(
            _problem(yaml_path, f"must be a positive number of metres per pixel, got {res!r}", key="resolution")
        )
    origin = meta.get("origin")
    if "origin" in meta and not (
        isinstance(origin, list)
        and len(origin) == 3
        and all(isinstance(v, int | float) and np.isfinite(v) for v in origin)
    ):
        problems.append(_problem(yaml_path, f"must be [x, y, yaw] numbers, got {origin!r}", key="origin"))
    negate = meta.get("negate", 0)
    if negate not in (0, 1, True, False):
        problems.append(_problem(yaml_path, f"must be 0 or 1, got {negate!r}", key="negate"))
    occ_t, free_t = meta.get("occupied_thresh", 0.65), meta.get("free_thresh", 0.196)
    for key, val in (("occupied_thresh", occ_t), ("free_thresh", free_t)):
        if not (isinstance(val, int | float) and 0 <= val <= 1):
            problems.append(_problem(yaml_path, f"must be a probability in [0, 1], got {val!r}", key=key))
    if isinstance(occ_t, int | float) and isinstance(free_t, int | float) and free_t >= occ_t:
        problems.append(
            _problem(yaml_path, f"free_thresh {free_t} must be below occupied_thresh {occ_t}", key="free_thresh")
        )
    mode = meta.get("mode", "trinary")
    if mode not in _MODES:
        problems.append(_problem(yaml_path, f"must be one of {_MODES}, got {mode!r}", key="mode"))
    image_path = None
    if isinstance(meta.get("image"), str):
        image_path = Path(meta["image"])
        if not image_path.is_absolute():
            image_path = yaml_path.parent / image_path
        if not image_path.is_file():
            problems.append(_problem(yaml_path, f"image '{meta['image']}' does not exist ({image_path})", key="image"))
    elif "image" in meta:
        problems.append(_problem(yaml_path, f"must be a file name, got {meta['image']!r}", key="image"))
    pixels = alpha = None
    if image_path is not None and image_path.is_file():
        try:
            pixels, alpha = _load_image(image_path)
        except ImageError as exc:
            problems.append(_problem(image_path, f"unreadable map image: {exc.message}", fix=exc.fix))
        except ValueError as exc:  # a mode PIL cannot convert to RGB (LAB, for one)
            problems.append(_problem(image_path, f"unreadable map image: {exc}", fix="save it as 8-bit PGM or PNG"))
    if problems:
        raise InputError(f"{yaml_path}: invalid map", problems)

    p = pixels / 255.0 if negate else (255.0 - pixels) / 255.0
    grid = np.full(p.shape, UNKNOWN, dtype=np.int8)
    if mode == "raw":
        grid = np.where(pixels <= 100, pixels, UNKNOWN).astype(np.int8)
    else:
        grid[p > occ_t] = OCCUPIED
        grid[p < free_t] = FREE
        if mode == "scale":
            mid = (p >= free_t) & (p <= occ_t)
            grid[mid] = (1 + np.rint(98 * (p[mid] - free_t) / (occ_t - free_t))).astype(np.int8)
            if alpha is not None:
                grid[alpha < 255] = UNKNOWN
    return OccupancyMap(
        grid=np.ascontiguousarray(grid[::-1]),
        resolution=float(res),
        origin_x=float(origin[0]),
        origin_y=float(origin[1]),
        origin_yaw=float(origin[2]),
    )


def _load_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Grey levels 0-255 and the alpha channel if any. 16-bit and float images are refused (by
    `pipeline.io.images`): map_server reads 8-bit values, and the thresholds and raw mode assume them."""
    from pipeline.io.images import open_image

    im = open_image(path, rgb=False)
    alpha = np.asarray(im.getchannel("A"), dtype=np.uint8) if "A" in im.getbands() else None
    gray = (
        np.asarray(im.convert("RGB"), dtype=np.float64).mean(axis=2)
        if im.mode != "L"
        else np.asarray(im, dtype=np.float64)
    )
    return gray, alpha


def write_map(yaml_path: Path, occ_map: OccupancyMap, image_name: str | None = None) -> Path:
    """Write a trinary map as map_saver does: occupied 0, free 254, unknown 205; thresholds 0.65/0.196."""
    from PIL import Image

    yaml_path = Path(yaml_path)
    image_name = image_name or yaml_path.with_suffix(".pgm").name
    pixels = np.full(occ_map.grid.shape, 205, dtype=np.uint8)
    pixels[occ_map.free] = 254
    pixels[occ_map.occupied] = 0
    with atomic_file(yaml_path.parent / image_name, "wb") as fh:
        Image.fromarray(pixels[::-1].copy(), mode="L").save(fh, format="PPM")
    doc = {
        "image": image_name,
        "mode": "trinary",
        "resolution": float(occ_map.resolution),
        "origin": [float(occ_map.origin_x), float(occ_map.origin_y), float(occ_map.origin_yaw)],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    return write_text_atomic(yaml_path, yaml.safe_dump(doc, sort_keys=False))
