"""`export-colmap`: a site's views as a posed COLMAP model (no 3D points), written by pycolmap.

The model has one rig of one camera per view index: a rig sensor is a camera id in COLMAP, so view k uses
camera k + 1, all with the site's intrinsics (principal point + 0.5 px: COLMAP puts pixel centres at
integer + 0.5, siteloc at integers): PINHOLE, or OPENCV when site.yaml gives a distortion (FULL_OPENCV if its
k3 is not zero). Each stop is one frame whose rig pose is the stop's mean position at
`camera_height` and its mean heading; the rig's sensors turn by `rig.yaw_offsets_deg`, so an image's pose is
the nominal rig pose (captured headings agree with it within `ingest.heading_tolerance_deg`). Image names
are relative to SITE_DIR/images when every image lies there, else to SITE_DIR. Triangulating points from
these known poses (hloc, `colmap point_triangulator`) is left to those tools.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pycolmap

from pipeline.colmap.align import cam_from_map
from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, Problems
from pipeline.io.atomic import atomic_dir, check_output
from pipeline.io.captures import CaptureRow, check_stops, read_captures
from pipeline.io.site import Camera, Site, read_site
from pipeline.runtime.motion import wrap_angle

RIG_ID = 1
DEFAULT_CAMERA_HEIGHT_M = 1.2


def read_views(root: Path, cfg: SitelocConfig) -> tuple[Site, list[CaptureRow]]:
    """The site and its views from captures.csv, or from images.parquet of an `ingest` output."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(
            f"{root}: site directory not found",
            [Problem(str(root), "not a directory", fix="pass a site capture directory or an ingest output")],
        )
    site = read_site(root / "site.yaml")
    problems = Problems()
    csv_path = root / "captures.csv"
    if csv_path.is_file() or not (root / "images.parquet").is_file():
        rows = read_captures(csv_path, problems)
        source = csv_path
    else:
        from pipeline.io import tables

        source = root / "images.parquet"
        t = tables.read_table(source, "images").to_pydict()
        rows = [
            CaptureRow(
                i + 2,
                t["image_id"][i],
                t["stop_id"][i],
                int(t["view"][i]),
                t["x"][i],
                t["y"][i],
                t["theta"][i],
                t["room"][i] or "",
                t["area"][i] or "",
            )
            for i in range(len(t["image_id"]))
        ]
    ing = cfg.ingest
    check_stops(source, rows, site, ing.position_tolerance_m, ing.heading_tolerance_deg, problems)
    problems.raise_if_any(f"{source}: the views cannot be exported; nothing was written")
    return site, rows


def image_names(rows: list[CaptureRow]) -> tuple[str, dict[str, str]]:
    """The image root (`images` or `.`, relative to SITE_DIR) and each image's COLMAP name under it."""
    if all(r.image.startswith("images/") for r in rows):
        return "images", {r.image: r.image[len("images/") :] for r in rows}
    return ".", {r.image: r.image for r in rows}


def colmap_camera(cam: Camera) -> tuple[str, list[float]]:
    """COLMAP's model and parameters of site.yaml's camera: PINHOLE, or OPENCV for a plumb_bob distortion
    (FULL_OPENCV with k4 = k5 = k6 = 0 when k3 is not zero: the same model)."""
    pinhole = [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5]
    if cam.distortion is None:
        return "PINHOLE", pinhole
    k1, k2, p1, p2, k3 = cam.distortion.coeffs
    if k3 == 0:
        return "OPENCV", pinhole + [k1, k2, p1, p2]
    return "FULL_OPENCV", pinhole + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


def build_reconstruction(site: Site, rows: list[CaptureRow], names: dict[str, str], camera_height: float):
    """The pycolmap.Reconstruction of the views: cameras 1..n_views, rig 1, one registered frame per stop."""
    if site.camera is None:
        raise InputError(f"site '{site.name}' has no camera", [Problem(
            "site.yaml", "a laser-only site has no images for COLMAP", fix="export a site with captures")])
    rec = pycolmap.Reconstruction()
    cam = site.camera
    offsets = site.rig.yaw_offsets
    model, params = colmap_camera(cam)
    for view in range(len(offsets)):
        rec.add_camera(
            pycolmap.Camera(camera_id=view + 1, model=model, width=cam.width, height=cam.height, params=params)
        )
    rig = pycolmap.Rig(rig_id=RIG_ID)
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1))
    cam0_from_map0 = cam_from_map(0.0, 0.0, 0.0, offsets[0])
    for view in range(1, len(offsets)):
        camk_from_cam0 = cam_from_map(0.0, 0.0, 0.0, offsets[view]) * cam0_from_map0.inverse()
        rig.add_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, view + 1), camk_from_cam0)
    rec.add_rig(rig)

    by_stop: dict[str, list[int]] = defaultdict(list)
    for i, r in enumerate(rows):
        by_stop[r.stop_id].append(i)
    for frame_id, members in enumerate(by_stop.values(), start=1):
        stop = [rows[i] for i in members]
        x = float(np.mean([r.x for r in stop]))
        y = float(np.mean([r.y for r in stop]))
        base = wrap_angle(np.array([r.theta - offsets[r.view] for r in stop]))
        heading = math.atan2(float(np.sin(base).mean()), float(np.cos(base).mean()))
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=RIG_ID)
        frame.rig_from_world = cam_from_map(x, y, camera_height, heading + offsets[0])
        for i in members:
            sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, rows[i].view + 1)
            frame.add_data_id(pycolmap.data_t(sensor, i + 1))
        rec.add_frame(frame)
        for i in members:
            image = pycolmap.Image(name=names[rows[i].image], camera_id=rows[i].view + 1, image_id=i + 1)
            image.frame_id = frame_id
            rec.add_image(image)
        rec.register_frame(frame_id)
    return rec


def run_export_colmap(
    cfg: SitelocConfig,
    *,
    inputs: dict[str, Path],
    outputs: dict[str, Path],
    force: bool = False,
    camera_height: float = DEFAULT_CAMERA_HEIGHT_M,
    text: bool = False,
) -> Path:
    """Write `outputs['out']`: the views of `inputs['site']` as a COLMAP model (binary, or text with `text`)."""
    if not (math.isfinite(camera_height) and camera_height >= 0):
        raise InputError(
            "invalid camera height",
            [Problem("--camera-height", f"must be a finite height in metres >= 0, got {camera_height}")],
        )
    site, rows = read_views(inputs["site"], cfg)
    _, names = image_names(rows)
    rec = build_reconstruction(site, rows, names, camera_height)
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        if text:
            rec.write_text(str(tmp))
        else:
            rec.write(str(tmp))
        write_effective_config(cfg, tmp, stage="export_colmap", inputs={**inputs, "camera_height_m": camera_height})
    return out
