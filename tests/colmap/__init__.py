"""COLMAP models in and out (`ingest-colmap`, `export-colmap`) on the tiny generated capture site.

Helpers shared by the modules here: the site, its captures as a dict, a model built with pycolmap directly
(one trivial frame per image, so stops come from positions) and anchors files.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from pipeline.config import load_config

CFG = load_config("demo")


def read_rows(path: Path) -> dict[str, dict]:
    """captures.csv (or anchors.csv) as image -> row, numbers parsed."""
    with Path(path).open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in ("x", "y", "theta"):
            r[k] = float(r[k])
        if "view" in r:
            r["view"] = int(r["view"])
    return {r["image"]: r for r in rows}


def stops_of(rows: dict[str, dict]) -> set[frozenset[tuple[str, int]]]:
    """The stops as sets of (image, view): comparable whatever the stop ids are called."""
    by_stop: dict[str, set] = {}
    for r in rows.values():
        by_stop.setdefault(r["stop_id"], set()).add((r["image"], r["view"]))
    return {frozenset(s) for s in by_stop.values()}


def angle_diff(a: float, b: float) -> float:
    return abs(math.atan2(math.sin(a - b), math.cos(a - b)))


def write_anchors(path: Path, site: Path, images: list[str], **shift) -> Path:
    """An anchors.csv of some of the site's images with their captured poses (plus `shift` per column)."""
    rows = read_rows(site / "captures.csv")
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "x", "y", "theta"])
        for name in images:
            r = rows[name]
            w.writerow([name] + [r[k] + shift.get(k, 0.0) for k in ("x", "y", "theta")])
    return Path(path)


def random_sim3(rng):
    """A similarity with a random rotation about any 3-D axis, scale in [0.2, 5] and translation."""
    import numpy as np
    import pycolmap

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rot = pycolmap.Rotation3d(axis * rng.uniform(0.3, 3.0))
    return pycolmap.Sim3d(float(rng.uniform(0.2, 5.0)), rot, rng.normal(scale=10.0, size=3))


def trivial_frame_model(site: Path, camera_height: float = 1.2, model: str = "PINHOLE", adjust=None):
    """A pycolmap.Reconstruction of the site's views without rigs: one camera, one trivial frame per image.

    `adjust` maps image paths of captures.csv to {"x": dx, "y": dy, "theta": dtheta} added to their poses.
    """
    import pycolmap

    from pipeline.colmap.align import cam_from_map

    rec = pycolmap.Reconstruction()
    params = [40.0, 40.0, 32.5, 24.5] if model == "PINHOLE" else [40.0, 32.5, 24.5, 0.01]
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model=model, width=64, height=48, params=params))
    for i, (name, r) in enumerate(sorted(read_rows(site / "captures.csv").items()), start=1):
        d = (adjust or {}).get(name, {})
        pose = cam_from_map(
            r["x"] + d.get("x", 0.0), r["y"] + d.get("y", 0.0), camera_height, r["theta"] + d.get("theta", 0.0)
        )
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name.removeprefix("images/"), camera_id=1, image_id=i), pose
        )
    return rec
