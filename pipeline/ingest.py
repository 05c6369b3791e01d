"""Stage `ingest`: validate a site capture directory and write the normalised tables, map and report.

Every problem is collected before anything is written; with any problem the stage raises
`InputError` listing all of them and leaves no output. The output directory appears only when
complete (`atomic_dir`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import IngestConfig, SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, Problems
from pipeline.io import tables
from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
from pipeline.io.capture_runs import CaptureRun, read_run
from pipeline.io.captures import (
    CaptureRow,
    check_images,
    check_poses,
    check_rows,
    check_stops,
    read_captures,
    split_stops,
)
from pipeline.io.coco import Box, read_coco_boxes
from pipeline.io.map_yaml import OccupancyMap, read_map, write_map
from pipeline.io.site import Site, read_site, write_site

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


@dataclass
class ValidatedSite:
    root: Path
    site: Site
    occ_map: OccupancyMap
    rows: list[CaptureRow]
    image_info: dict[str, tuple[int, int, str]]
    boxes: list[Box]
    runs: list[CaptureRun]
    warnings: list[Problem] = field(default_factory=list)


def validate_site_dir(root: Path, cfg: IngestConfig, *, progress: bool = True) -> ValidatedSite:
    """Check everything in a capture directory; raise one `InputError` listing every problem."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(
            f"{root}: site directory not found",
            [Problem(str(root), "not a directory", fix="pass the folder holding site.yaml")],
        )
    problems = Problems()
    site = occ_map = None
    try:
        site = read_site(root / "site.yaml")
    except InputError as exc:
        problems.extend(exc.problems)
    try:
        occ_map = read_map(root / "map.yaml")
    except InputError as exc:
        problems.extend(exc.problems)

    csv_path = root / "captures.csv"
    laser_only = site is not None and site.camera is None
    rows = read_captures(csv_path, problems, allow_empty=laser_only)
    check_rows(root, csv_path, rows, problems)
    if occ_map is not None:
        check_poses(csv_path, rows, occ_map, problems)
    if site is not None:
        check_stops(csv_path, rows, site, cfg.position_tolerance_m, cfg.heading_tolerance_deg, problems)
    image_info = check_images(root, csv_path, rows, site, cfg.decode_images, problems, progress=progress)

    boxes: list[Box] = []
    coco_path = root / "annotations.json"
    if coco_path.is_file() and rows:  # without captures there is nothing to check the annotations against
        boxes = read_coco_boxes(coco_path, site, image_info, {r.image for r in rows}, cfg.min_box_side_px, problems)
    else:
        problems.warn(coco_path, "no annotations.json: the detector cannot be trained on this site")

    runs: list[CaptureRun] = []
    runs_dir = root / "runs"
    if runs_dir.is_dir():
        for run_dir in sorted(p for p in runs_dir.iterdir() if p.is_dir()):
            run = read_run(run_dir, root, site, occ_map, problems)
            if run is not None:
                runs.append(run)

    if laser_only and not rows and not runs:
        problems.add(runs_dir, "a laser-only site (no camera in site.yaml) has no runs",
                     fix="add runs/<run>/ (trajectory.csv + scans.npy) recorded by the robot")
    referenced = {r.image for r in rows} | {i for run in runs for i in run.image if i}
    images_dir = root / "images"
    if images_dir.is_dir():
        stray = [
            p
            for p in images_dir.rglob("*")
            if p.suffix.lower() in IMAGE_SUFFIXES and p.relative_to(root).as_posix() not in referenced
        ]
        if stray:
            problems.warn(
                images_dir,
                f"{len(stray)} images are not listed in captures.csv or a run "
                f"(e.g. {stray[0].relative_to(root).as_posix()}); they are ignored",
            )

    problems.raise_if_any(f"{root}: the capture directory has problems; nothing was written")
    assert site is not None and occ_map is not None
    return ValidatedSite(root, site, occ_map, rows, image_info, boxes, runs, problems.warnings)


def _link_or_copy(src: Path, dst: Path, link: bool) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if link:
        try:
            os.link(src, dst)
            return
        except OSError:
            pass  # another file system or no hard links: copy instead
    shutil.copy2(src, dst)


def _images_table(v: ValidatedSite, split: dict[str, str]):
    rows = v.rows
    return tables.to_table(
        "images",
        {
            "image_id": [r.image for r in rows],
            "stop_id": [r.stop_id for r in rows],
            "view": [r.view for r in rows],
            "x": [r.x for r in rows],
            "y": [r.y for r in rows],
            "theta": [r.theta for r in rows],
            "room": [r.room or None for r in rows],
            "area": [r.area or None for r in rows],
            "split": [split[r.stop_id] for r in rows],
            "width": [v.image_info[r.image][0] for r in rows],
            "height": [v.image_info[r.image][1] for r in rows],
            "sha256": [v.image_info[r.image][2] for r in rows],
        },
        metadata={"site": v.site.name},
    )


def _boxes_table(v: ValidatedSite):
    b = v.boxes
    return tables.to_table(
        "boxes",
        {
            "image_id": [x.image_id for x in b],
            "class_id": [x.class_id for x in b],
            "class_name": [x.class_name for x in b],
            "x1": [x.x1 for x in b],
            "y1": [x.y1 for x in b],
            "x2": [x.x2 for x in b],
            "y2": [x.y2 for x in b],
        },
        metadata={"site": v.site.name, "classes": json.dumps(list(v.site.classes))},
    )


def _run_table(run: CaptureRun, site: Site):
    return run_table(run, site.laser, site.name)


def run_table(run: CaptureRun, laser, site_name: str, first_step: int = 0):
    """The `runs` table of one run (or of its part from step `first_step` on); ranges past the laser's
    range_max (or non-finite) become range_max."""
    n = len(run.t)
    ranges = np.asarray(run.ranges, dtype=np.float32)
    ranges = np.where(np.isfinite(ranges), np.minimum(ranges, laser.range_max), laser.range_max)
    gt = [None if np.isnan(v) else float(v) for v in run.gt.ravel()]
    return tables.to_table(
        "runs",
        {
            "run": [run.name] * n,
            "step": np.arange(first_step, first_step + n),
            "t": run.t,
            "odom_x": run.odom[:, 0],
            "odom_y": run.odom[:, 1],
            "odom_theta": run.odom[:, 2],
            "gt_x": gt[0::3],
            "gt_y": gt[1::3],
            "gt_theta": gt[2::3],
            "ranges": tables.list_column(ranges.astype(np.float32)),
            "angle_min": [laser.angle_min] * n,
            "angle_increment": [laser.angle_increment] * n,
            "range_max": [laser.range_max] * n,
            "image_id": run.image,
            "kidnapped": run.kidnapped,
        },
        metadata={"site": site_name, "odometry": "recorded"},
    )


def _report(v: ValidatedSite, split: dict[str, str]) -> dict:
    per_split = Counter(split.values())
    return {
        "site": v.site.name,
        "images": len(v.rows),
        "stops": len(split),
        "stops_per_split": dict(sorted(per_split.items())),
        "rooms": len({r.room for r in v.rows if r.room}),
        "areas": len({(r.room, r.area) for r in v.rows if r.area}),
        "boxes": len(v.boxes),
        "boxes_per_class": {c: sum(b.class_name == c for b in v.boxes) for c in v.site.classes},
        "runs": {
            run.name: {
                "steps": len(run.t),
                "images": sum(i is not None for i in run.image),
                "with_ground_truth": int(np.sum(~np.isnan(run.gt[:, 0]))),
            }
            for run in v.runs
        },
        "map": {
            "width_cells": v.occ_map.width,
            "height_cells": v.occ_map.height,
            "resolution": v.occ_map.resolution,
            "free_share": round(float(v.occ_map.free.mean()), 4),
        },
        "warnings": [str(w) for w in v.warnings],
    }


def _report_md(rep: dict) -> str:
    lines = [f"# Ingest report: {rep['site']}", "", "| what | count |", "| --- | --- |"]
    for key in ("images", "stops", "rooms", "areas", "boxes"):
        lines.append(f"| {key} | {rep[key]} |")
    for s, n in rep["stops_per_split"].items():
        lines.append(f"| stops in {s} | {n} |")
    m = rep["map"]
    lines.append(f"| map | {m['width_cells']} x {m['height_cells']} cells at {m['resolution']} m |")
    lines += ["", "## Boxes per class", "", "| class | boxes |", "| --- | --- |"]
    lines += [f"| {c} | {n} |" for c, n in rep["boxes_per_class"].items()]
    if rep["runs"]:
        lines += ["", "## Runs", "", "| run | steps | images | with ground truth |", "| --- | --- | --- | --- |"]
        lines += [f"| {k} | {r['steps']} | {r['images']} | {r['with_ground_truth']} |" for k, r in rep["runs"].items()]
    if rep["warnings"]:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in rep["warnings"]]
    return "\n".join(lines) + "\n"


def run_ingest(
    cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], force: bool = False, progress: bool = True
) -> Path:
    """Validate `inputs['site']` and write `outputs['out']`: images/boxes/runs tables, map, site, report."""
    from pipeline.progress import progress_bar

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    v = validate_site_dir(inputs["site"], cfg.ingest, progress=progress)
    split = split_stops([r.stop_id for r in v.rows], cfg.ingest.split.test_fraction, cfg.ingest.split.seed)
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        to_copy = sorted({r.image for r in v.rows} | {i for run in v.runs for i in run.image if i})
        for rel in progress_bar(to_copy, desc="linking images", unit="img", enabled=progress, leave=False):
            _link_or_copy(v.root / rel, tmp / rel, cfg.ingest.link_images)
        tables.write_table(tmp / "images.parquet", _images_table(v, split), "images")
        tables.write_table(tmp / "boxes.parquet", _boxes_table(v), "boxes")
        for run in v.runs:
            tables.write_table(tmp / "runs" / f"{run.name}.parquet", _run_table(run, v.site), "runs")
        write_map(tmp / "map.yaml", v.occ_map)
        write_site(tmp / "site.yaml", v.site)
        rep = _report(v, split)
        write_text_atomic(tmp / "report.json", json.dumps(rep, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", _report_md(rep))
        write_effective_config(cfg, tmp, stage="ingest", inputs=inputs)
    return out
