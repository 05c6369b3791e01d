"""Poses between COLMAP and the map frame, and the similarity `map_from_model` fitted on anchor images.

COLMAP stores `cam_from_world` with the camera looking along +z, x right, y down. The map frame is the one of
map.yaml with z up, so a camera's heading is its optical axis projected on the floor. A reconstruction has an
arbitrary scale, rotation and origin; images with known map poses (anchors) fix them: pycolmap's
`estimate_sim3d` fits the camera centres to (x, y, 0). The camera height is unknown but constant, so it ends
up in the translation. Anchor headings are not fitted; they check the result (a wrong up axis or a mirrored
model shows there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from pipeline.errors import InputError, Problem, Problems, excerpt
from pipeline.io.captures import parse_pose
from pipeline.io.text_files import read_csv
from pipeline.runtime.motion import wrap_angle

ANCHOR_COLUMNS = ("image", "x", "y", "theta")
MIN_ANCHORS = 3
MIN_HORIZONTAL = 1e-3  # an optical axis with less horizontal extent than this (unit vector) has no heading


def cam_from_map(x: float, y: float, z: float, theta: float) -> pycolmap.Rigid3d:
    """COLMAP pose of a camera at (x, y, z) in the map frame looking horizontally along heading `theta`."""
    c, s = math.cos(theta), math.sin(theta)
    # Rows: the camera's x (right), y (down) and z (optical axis) in map coordinates.
    rot = np.array([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rot), -rot @ np.array([x, y, z], dtype=np.float64))


def map_pose(cam_from_model: pycolmap.Rigid3d, map_from_model: pycolmap.Sim3d) -> tuple[np.ndarray, float | None]:
    """Camera centre (x, y, z) in the map frame and heading (radians); heading None if the camera looks straight up
    or down."""
    map_from_cam = map_from_model.transform_camera_world(cam_from_model).inverse()
    axis = map_from_cam.rotation * np.array([0.0, 0.0, 1.0])
    horizontal = math.hypot(axis[0], axis[1])
    heading = math.atan2(axis[1], axis[0]) if horizontal >= MIN_HORIZONTAL else None
    return np.asarray(map_from_cam.translation, dtype=np.float64), heading


def upright(cam_from_model: pycolmap.Rigid3d, map_from_model: pycolmap.Sim3d) -> bool:
    """Whether the image's up direction (camera -y) points up in the map frame. Cameras of a rig are upright, so
    most of them upside down means a mirrored fit: anchors whose y grows downwards, as image rows do."""
    map_from_cam = map_from_model.transform_camera_world(cam_from_model).inverse()
    return bool((map_from_cam.rotation * np.array([0.0, -1.0, 0.0]))[2] > 0.0)


@dataclass(frozen=True)
class Anchor:
    """An image whose map pose is known: `image` is the COLMAP image name it matched."""

    line: int
    image: str
    x: float
    y: float
    theta: float


def read_anchors(path: Path, names: set[str], problems: Problems) -> list[Anchor]:
    """Parse anchors.csv (image, x, y, theta; other columns are ignored, so a captures.csv works too).

    An anchor names a COLMAP image; a site-relative `images/NAME` matches the image NAME as well.
    """
    path = Path(path)
    if not path.is_file():
        problems.add(path, "anchors file is missing", fix="pass a CSV with columns image,x,y,theta")
        return []
    anchors: list[Anchor] = []
    seen: dict[str, int] = {}
    table = read_csv(path, problems)
    if table is None:
        return []
    missing = [c for c in ANCHOR_COLUMNS if c not in table.header]
    if missing:
        problems.add(path, f"missing columns {missing} (found {excerpt(table.header, 200)})", row=1,
                     fix="the header needs image,x,y,theta")
        return []
    for line, rec in table.rows:
        bad: list[str] = []
        nums = parse_pose(rec, bad)
        name = rec["image"]
        if name not in names and name.startswith("images/") and name[len("images/") :] in names:
            name = name[len("images/") :]
        if not rec["image"]:
            bad.append("image is empty")
        elif name not in names:
            bad.append(f"image '{excerpt(rec['image'])}' is not in the COLMAP model")
        elif name in seen:
            bad.append(f"image '{excerpt(rec['image'])}' is listed twice (first on line {seen[name]})")
        if bad:
            problems.add(
                path, "; ".join(bad), row=line, fix="correct the row or remove it (names as in images.txt)"
            )
            continue
        seen[name] = line
        anchors.append(Anchor(line, name, nums["x"], nums["y"], nums["theta"]))
    return anchors


def check_anchor_layout(path: Path, anchors: list[Anchor], tol_m: float, problems: Problems) -> None:
    """At least three anchors, not all on one line: otherwise the similarity is not determined."""
    if len(anchors) < MIN_ANCHORS:
        problems.add(
            path,
            f"{len(anchors)} usable anchors, the alignment needs at least {MIN_ANCHORS}",
            fix="list at least 3 images with known map poses, spread over the site",
        )
        return
    xy = np.array([[a.x, a.y] for a in anchors])
    xy = xy - xy.mean(axis=0)
    sv = np.linalg.svd(xy, compute_uv=False)
    off_line_rms = float(sv[1] / math.sqrt(len(anchors))) if len(sv) > 1 else 0.0
    if off_line_rms <= tol_m:
        where = "at one position" if sv[0] / math.sqrt(len(anchors)) <= tol_m else "on one line"
        problems.add(
            path,
            f"the anchors lie {where} (RMS distance from their best line {off_line_rms:.3f} m, "
            f"tolerance {tol_m} m): their poses do not determine the rotation about that line",
            fix="add an anchor away from the line through the others (views of one stop share one position)",
        )


def _off_plane_shift(points: np.ndarray) -> np.ndarray:
    """A translation taking `points` [n, 3] off any plane through the origin: centred, then moved by their spread
    along the normal of their best plane."""
    centred = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=True)
    spread = max(float(sv[0]) / math.sqrt(len(points)), 1e-9)
    return -points.mean(axis=0) + vt[-1] * spread


def fit_map_from_model(model_xyz: np.ndarray, map_xy: np.ndarray) -> pycolmap.Sim3d | None:
    """Least-squares similarity taking model camera centres [n, 3] to map points (x, y, 0); None if degenerate.

    pycolmap's `estimate_sim3d` refuses point sets whose coordinates (not centred) have rank < 3, which is
    every set of camera centres at one height seen from an origin in their plane (map points at z = 0; a
    normalised model). Both sides are translated off such planes first and the translations composed back;
    the least-squares fit is translation-equivariant, so the result is the same similarity.
    """
    src = np.asarray(model_xyz, dtype=np.float64)
    tgt = np.column_stack([np.asarray(map_xy, dtype=np.float64), np.zeros(len(map_xy))])
    if len(src) < MIN_ANCHORS:
        return None
    src_shift, tgt_shift = _off_plane_shift(src), _off_plane_shift(tgt)
    shifted = pycolmap.estimate_sim3d(src + src_shift, tgt + tgt_shift)
    if shifted is None:
        return None
    ident = pycolmap.Rotation3d()
    return pycolmap.Sim3d(1.0, ident, -tgt_shift) * shifted * pycolmap.Sim3d(1.0, ident, src_shift)


@dataclass(frozen=True)
class AnchorResidual:
    image: str
    position_error_m: float
    heading_error: float | None  # radians; None if the camera has no heading (looks straight up or down)


@dataclass(frozen=True)
class Alignment:
    """`map_from_model` and how well it puts the anchors where they belong."""

    map_from_model: pycolmap.Sim3d
    fitted: bool
    residuals: list[AnchorResidual]

    def summary(self) -> dict:
        """JSON-ready: the transform and per-anchor residuals (metres, degrees), RMS and max."""
        pos = np.array([r.position_error_m for r in self.residuals])
        head = np.degrees([abs(r.heading_error) for r in self.residuals if r.heading_error is not None])

        def stats(v: np.ndarray) -> dict:
            if not len(v):
                return {"rms": None, "max": None}
            return {"rms": float(np.sqrt(np.mean(v**2))), "max": float(v.max())}

        return {
            "method": "sim3 fitted on anchor camera centres" if self.fitted else "none (--in-map-frame)",
            "scale": float(self.map_from_model.scale),
            "map_from_model": np.asarray(self.map_from_model.matrix()).tolist(),
            "anchors": [
                {
                    "image": r.image,
                    "position_error_m": r.position_error_m,
                    "heading_error_deg": None if r.heading_error is None else math.degrees(abs(r.heading_error)),
                }
                for r in self.residuals
            ],
            "position_error_m": stats(pos),
            "heading_error_deg": stats(head),
        }


def align(
    poses: dict[str, pycolmap.Rigid3d], anchors: list[Anchor], *, fit: bool, anchors_path: Path | None = None
) -> Alignment:
    """Fit `map_from_model` on the anchors (`fit`), or take the model as already in the map frame; residuals of
    every anchor either way. `poses` maps image names to their `cam_from_world` in the model."""
    map_from_model = pycolmap.Sim3d()
    if fit:
        src = np.array([poses[a.image].inverse().translation for a in anchors])
        sim = fit_map_from_model(src, np.array([[a.x, a.y] for a in anchors]))
        if sim is None or not np.all(np.isfinite(sim.matrix())) or float(sim.scale) <= 0:
            raise InputError(
                f"{anchors_path}: the anchors' camera centres in the model do not fit their map positions",
                [
                    Problem(
                        str(anchors_path),
                        "no similarity maps the model's anchor cameras to the map",
                        fix="check that the anchors' images and poses belong together",
                    )
                ],
            )
        map_from_model = sim
    residuals = []
    for a in anchors:
        centre, heading = map_pose(poses[a.image], map_from_model)
        err = None if heading is None else float(wrap_angle(heading - a.theta))
        residuals.append(AnchorResidual(a.image, float(math.hypot(centre[0] - a.x, centre[1] - a.y)), err))
    return Alignment(map_from_model, fit, residuals)
