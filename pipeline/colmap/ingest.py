"""`ingest-colmap`: a COLMAP reconstruction becomes a site capture directory that `siteloc ingest` accepts.

The model is read by pycolmap, brought into the map frame (`align`), and its images are grouped into stops:
one rig frame is one stop when the model has frames of several images, else images whose centres lie within
`ingest.position_tolerance_m` form a stop. Stops without exactly one image per rig view, or whose headings
disagree with the rig, are listed in report.json and left out of captures.csv. Every problem with the inputs
is reported at once before anything is written; the output appears only when complete (`atomic_dir`).
site.yaml holds the model's one camera: radial and OpenCV models keep their coefficients as its plumb_bob
`distortion` (the images are linked as they are, not undistorted).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from pydantic import ValidationError

from pipeline.colmap.align import align, check_anchor_layout, map_pose, read_anchors, upright
from pipeline.colmap.report import alignment_warnings, build_report, report_md
from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, Problems
from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
from pipeline.io.captures import site_relative
from pipeline.io.map_yaml import OCCUPIED, OccupancyMap, read_map, write_map
from pipeline.io.site import Camera, Distortion, Site, validation_problems, write_site
from pipeline.runtime.motion import wrap_angle

# COLMAP models site.yaml can hold, and where their parameters go: (fx, fy, cx, cy), then plumb_bob's
# (k1, k2, p1, p2, k3) by parameter index (None: 0; fy of a one-focal model is its f).
CAMERA_PARAMS = {
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), None),
    "PINHOLE": ((0, 1, 2, 3), None),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), (3, None, None, None, None)),
    "RADIAL": ((0, 0, 1, 2), (3, 4, None, None, None)),
    "OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7, None)),
    "FULL_OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7, 8)),  # only with k4 = k5 = k6 = 0 (params 9-11): plumb_bob
}
SUPPORTED_MODELS = tuple(CAMERA_PARAMS)
MODEL_FILES = ("cameras", "images", "points3D")
INTRINSICS_TOL_PX = 1e-3  # cameras of one model must agree this well: site.yaml holds one camera
MAX_LISTED = 10  # missing images listed one by one before "and N more"


@dataclass(frozen=True)
class View:
    """A posed image of the model, in the map frame."""

    name: str
    camera_id: int
    frame_id: int
    xyz: np.ndarray
    theta: float


@dataclass
class Stop:
    views: list[tuple[int, View]]  # (rig view index, image); index -1: the image's sensor is not in the rig
    frame_id: int | None = None
    reasons: list[str] = field(default_factory=list)
    stop_id: str = ""


def read_model(model_dir: Path) -> pycolmap.Reconstruction:
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise InputError(
            f"{model_dir}: COLMAP model not found",
            [Problem(str(model_dir), "not a directory", fix="pass the folder holding cameras, images and points3D")],
        )
    missing = [f for f in MODEL_FILES if not any((model_dir / f"{f}{e}").is_file() for e in (".bin", ".txt"))]
    if missing:
        models = sorted(p for p in model_dir.iterdir() if any(p.glob("cameras.bin")) or any(p.glob("cameras.txt")))
        fix = f"pass one model folder, e.g. {models[0]}" if models else "pass COLMAP's model folder (e.g. sparse/0)"
        raise InputError(
            f"{model_dir}: not a COLMAP model",
            [Problem(str(model_dir), f"missing {', '.join(f + '.bin or .txt' for f in missing)}", fix=fix)],
        )
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except (ValueError, RuntimeError, OSError) as exc:
        raise InputError(
            f"{model_dir}: unreadable COLMAP model",
            [
                Problem(
                    str(model_dir), f"pycolmap cannot read it: {exc}", fix="re-export it with colmap model_converter"
                )
            ],
        ) from None


def site_camera(rec: pycolmap.Reconstruction, camera_ids: set[int], where: Path, problems: Problems) -> Camera | None:
    """The one camera of site.yaml, from the model's cameras (pixel centres moved from +0.5 to 0); a radial
    or OpenCV model becomes its plumb_bob distortion."""
    found: dict[int, tuple[float, ...]] = {}
    for cid in sorted(camera_ids):
        cam = rec.camera(cid)
        params = [float(p) for p in cam.params]
        if cam.model_name not in CAMERA_PARAMS or (cam.model_name == "FULL_OPENCV" and any(params[9:])):
            what = "a FULL_OPENCV camera with k4, k5, k6 not zero" if cam.model_name == "FULL_OPENCV" else (
                f"a {cam.model_name} camera")
            problems.add(
                where,
                f"camera {cid} is {what}; supported models: {', '.join(SUPPORTED_MODELS)} (k4 = k5 = k6 = 0)",
                fix="undistort the model first: colmap image_undistorter --image_path IMAGES --input_path MODEL "
                "--output_path UNDIST, then pass UNDIST/sparse and --images UNDIST/images",
            )
            continue
        focal, dist = CAMERA_PARAMS[cam.model_name]
        fx, fy, cx, cy = (params[i] for i in focal)
        coeffs = (0.0,) * 5 if dist is None else tuple(0.0 if i is None else params[i] for i in dist)
        found[cid] = (cam.width, cam.height, fx, fy, cx - 0.5, cy - 0.5, *coeffs)
    if not found:
        return None
    first_id, first = next(iter(found.items()))
    # Intrinsics compared in pixels, coefficients scaled by the image size (about the pixels they move an edge).
    scale = np.r_[np.ones(6), np.full(5, max(first[0], first[1]))]
    differ = [cid for cid, k in found.items() if np.max(np.abs(np.subtract(k, first)) * scale) > INTRINSICS_TOL_PX]
    if differ:
        problems.add(
            where,
            f"cameras {differ} have other intrinsics than camera {first_id}; site.yaml holds one camera",
            fix="capture with one camera model, or ingest each camera's images as its own site",
        )
        return None
    w, h, fx, fy, cx, cy, *coeffs = first
    distortion = Distortion(coeffs=tuple(coeffs)) if any(coeffs) else None
    return Camera(width=int(w), height=int(h), fx=fx, fy=fy, cx=cx, cy=cy, distortion=distortion)


def group_stops(rec: pycolmap.Reconstruction, views: list[View], site: Site, tol_m: float) -> tuple[list[Stop], str]:
    """Stops by rig frame (a sensor's rank in its rig is its view: reference first, then by camera id), or by
    position (a view's index is the rig offset nearest its heading relative to the stop's first image)."""
    offsets = np.array(site.rig.yaw_offsets)
    by_frame: dict[int, list[View]] = defaultdict(list)
    for v in views:
        by_frame[v.frame_id].append(v)
    if any(len(m) > 1 for m in by_frame.values()):
        stops = []
        for fid, members in by_frame.items():
            rig = rec.rig(rec.frame(fid).rig_id)
            sensors = [rig.ref_sensor_id] + sorted(rig.non_ref_sensors)
            rank = {s.id: k for k, s in enumerate(sensors) if s.type == pycolmap.SensorType.CAMERA}
            stops.append(Stop([(rank.get(v.camera_id, -1), v) for v in members], frame_id=fid))
        return stops, "rig frames"
    clusters: list[list[View]] = []
    for v in sorted(views, key=lambda v: v.name):
        home = next((c for c in clusters if math.dist(c[0].xyz[:2], v.xyz[:2]) <= tol_m), None)
        if home is None:
            clusters.append([v])
        else:
            home.append(v)
    stops = []
    for members in clusters:
        base = members[0].theta - offsets[0]
        stops.append(Stop([(int(np.argmin(np.abs(wrap_angle(v.theta - base - offsets)))), v) for v in members]))
    return stops, f"positions within {tol_m} m"


def check_stop(stop: Stop, site: Site, occ: OccupancyMap, tol_m: float, tol_deg: float) -> None:
    """Fill `stop.reasons` with what keeps it out of captures.csv (what `check_stops` and `check_poses` refuse)."""
    offsets = np.array(site.rig.yaw_offsets)
    n = len(offsets)
    idx = [k for k, _ in stop.views]
    if len(idx) != n:
        stop.reasons.append(f"{len(idx)} images, the rig has {n} views")
    if -1 in idx:
        stop.reasons.append("images of a camera outside the frame's rig")
    dup = sorted({k for k in idx if k >= 0 and idx.count(k) > 1})
    if dup:
        stop.reasons.append(f"views {dup} taken by more than one image")
    missing = sorted(set(range(n)) - set(idx))
    if missing:
        stop.reasons.append(f"views {missing} missing")
    xy = np.array([v.xyz[:2] for _, v in stop.views])
    spread = float(np.max(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))
    if spread > tol_m:
        stop.reasons.append(f"images {spread:.3f} m apart (tolerance {tol_m} m)")
    valid = [(k, v) for k, v in stop.views if k >= 0]
    if len(valid) >= 2:
        base = wrap_angle(np.array([v.theta - offsets[k] for k, v in valid]))
        mean = math.atan2(np.sin(base).mean(), np.cos(base).mean())
        dev = float(np.degrees(np.max(np.abs(wrap_angle(base - mean)))))
        if dev > tol_deg:
            stop.reasons.append(
                f"headings disagree with the rig yaw offsets by {dev:.1f} deg (tolerance {tol_deg} deg)"
            )
    value = occ.value_at(xy[:, 0], xy[:, 1], outside=-2)
    if np.any(value == -2):
        stop.reasons.append("outside the map")
    elif np.any(value == OCCUPIED):
        stop.reasons.append("inside a wall (occupied map cell)")


def check_images(images_dir: Path, stops: list[Stop], camera: Camera, problems: Problems) -> None:
    """Every image of a kept stop exists under --images, inside it, with the camera's size."""
    from pipeline.io.images import ImageError, image_size

    missing = []
    for name in sorted(v.name for s in stops for _, v in s.views):
        full = site_relative(images_dir, name)
        if full is None:
            problems.add(images_dir, f"image name '{name}' is absolute or leaves the image folder")
        elif not full.is_file():
            missing.append(name)
        else:
            try:  # the header only, as before: the stages that decode the images name a damaged one
                size = image_size(full)
            except ImageError as exc:
                problems.add(full, f"unreadable image: {exc.message}", fix=exc.fix)
                continue
            if size != (camera.width, camera.height):
                problems.add(full, f"image is {size[0]}x{size[1]}, its COLMAP camera {camera.width}x{camera.height}")
    for name in missing[:MAX_LISTED]:
        problems.add(
            images_dir, f"image '{name}' of the model is missing", fix="pass the folder COLMAP read images from"
        )
    if len(missing) > MAX_LISTED:
        problems.add(images_dir, f"and {len(missing) - MAX_LISTED} more images of the model are missing")


def _rows(stops: list[Stop]) -> list[dict]:
    return [
        {
            "image": f"images/{v.name}",
            "stop_id": s.stop_id,
            "view": k,
            "x": round(float(v.xyz[0]), 9),
            "y": round(float(v.xyz[1]), 9),
            "theta": round(float(wrap_angle(v.theta)), 9),
            "room": "",
            "area": "",
        }
        for s in stops
        for k, v in sorted(s.views, key=lambda kv: kv[0])
    ]


def site_name(out: Path) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(out).resolve().name).strip("_") or "site"


def run_ingest_colmap(
    cfg: SitelocConfig,
    *,
    inputs: dict[str, Path],
    outputs: dict[str, Path],
    force: bool = False,
    progress: bool = True,
    in_map_frame: bool = False,
    name: str | None = None,
) -> Path:
    """Read `inputs['model']` (+ 'images', 'map', optional 'anchors') and write the capture directory
    `outputs['out']`: site.yaml, map.yaml + map.pgm, captures.csv, images/, report.json + report.md, config.yaml.
    With `in_map_frame` the model is taken as already in map coordinates with z up (as export-colmap writes it)."""
    from pipeline.ingest import _link_or_copy, validate_site_dir
    from pipeline.progress import progress_bar

    ing = cfg.ingest
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    model_dir, images_dir = Path(inputs["model"]), Path(inputs["images"])
    anchors_path = Path(inputs["anchors"]) if inputs.get("anchors") else None
    problems = Problems()
    occ = None
    try:
        occ = read_map(Path(inputs["map"]))
    except InputError as exc:
        problems.extend(exc.problems)
    if not images_dir.is_dir():
        problems.add(images_dir, "image folder not found", fix="pass --images, the folder COLMAP read the images from")
    if anchors_path is None and not in_map_frame:
        problems.add(
            "--anchors",
            "no anchors given",
            fix="pass --anchors anchors.csv, or --in-map-frame if the model is already in map coordinates with z up",
        )
    try:
        rec = read_model(model_dir)
    except InputError as exc:
        raise InputError(f"{exc.summary}; nothing was written", exc.problems + problems.items) from None
    posed = {im.name: im for im in rec.images.values() if im.has_pose}
    skipped = [
        {"image": n, "reason": "not registered (no pose)"}
        for n in sorted(im.name for im in rec.images.values() if not im.has_pose)
    ]
    where = next(model_dir / f"cameras{e}" for e in (".bin", ".txt") if (model_dir / f"cameras{e}").is_file())
    camera = site_camera(rec, {im.camera_id for im in posed.values()}, where, problems)
    if not posed:
        problems.add(model_dir, "the model has no registered images", fix="reconstruct the model first")
    anchors = read_anchors(anchors_path, set(posed), problems) if anchors_path is not None else []
    if anchors_path is not None and not in_map_frame:
        check_anchor_layout(anchors_path, anchors, ing.position_tolerance_m, problems)
    site = None
    if camera is not None:
        try:
            site = Site(name=name or site_name(out), camera=camera)
        except ValidationError as exc:
            problems.extend(validation_problems(Path("--name"), exc))
    problems.raise_if_any(f"{model_dir}: cannot ingest the COLMAP model; nothing was written")
    assert site is not None and occ is not None

    poses = {n: im.cam_from_world() for n, im in posed.items()}
    alignment = align(poses, anchors, fit=not in_map_frame, anchors_path=anchors_path)
    upside_down = sum(not upright(p, alignment.map_from_model) for p in poses.values())
    if alignment.fitted and upside_down > len(poses) / 2:
        problems.add(
            anchors_path,
            f"the fit turns {upside_down} of {len(poses)} cameras upside down: the anchors look mirrored",
            fix="anchors are map coordinates as in map.yaml (x right, y up), not image rows and columns",
        )
    views = []
    for n, im in sorted(posed.items()):
        xyz, theta = map_pose(poses[n], alignment.map_from_model)
        if theta is None:
            skipped.append({"image": n, "reason": "looks straight up or down: no heading"})
        else:
            views.append(View(n, im.camera_id, im.frame_id, xyz, theta))
    if not views:
        problems.add(model_dir, "every camera looks straight up or down in the map frame", fix="check the anchors")
    problems.raise_if_any(f"{model_dir}: the model does not align with the map; nothing was written")
    stops, grouping = group_stops(rec, views, site, ing.position_tolerance_m)
    stops.sort(key=lambda s: min(v.name for _, v in s.views))
    for k, s in enumerate(stops):
        s.stop_id = f"stop_{k:03d}"
        check_stop(s, site, occ, ing.position_tolerance_m, ing.heading_tolerance_deg)
    kept = [s for s in stops if not s.reasons]
    left_out = [s for s in stops if s.reasons]
    if not kept:
        for s in left_out[:MAX_LISTED]:
            problems.add(model_dir, f"{s.stop_id} ({min(v.name for _, v in s.views)}, ...): {'; '.join(s.reasons)}")
        if upside_down:
            problems.add(
                model_dir,
                f"{upside_down} of {len(poses)} cameras are upside down in the map frame",
                fix="pass --anchors, or give the model z up (COLMAP: model_aligner) before --in-map-frame",
            )
        problems.raise_if_any(
            f"{model_dir}: no complete stop ({len(stops)} found, grouped by {grouping}); nothing was written"
        )
    check_images(images_dir, kept, camera, problems)
    problems.raise_if_any(f"{images_dir}: images of the model are missing or wrong; nothing was written")

    warnings = alignment_warnings(alignment, views, ing, upside_down, len(left_out), len(stops))

    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        names = sorted(v.name for s in kept for _, v in s.views)
        for n in progress_bar(names, desc="linking images", unit="img", enabled=progress, leave=False):
            _link_or_copy(images_dir / n, tmp / "images" / n, ing.link_images)
        write_site(tmp / "site.yaml", site)
        write_map(tmp / "map.yaml", occ)
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=["image", "stop_id", "view", "x", "y", "theta", "room", "area"])
        writer.writeheader()
        writer.writerows(_rows(kept))
        write_text_atomic(tmp / "captures.csv", buf.getvalue())
        checked = validate_site_dir(tmp, ing.model_copy(update={"decode_images": False}), progress=False)
        warnings += [str(w).replace(str(tmp), str(out)) for w in checked.warnings]
        rep = build_report(site.name, rec, grouping, alignment, kept, left_out, skipped, views, upside_down, warnings)
        write_text_atomic(tmp / "report.json", json.dumps(rep, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", report_md(rep))
        write_effective_config(cfg, tmp, stage="ingest_colmap", inputs={k: v for k, v in inputs.items() if v})
    return out
