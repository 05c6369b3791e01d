"""`runs/<run>/` of a capture directory: a trajectory with odometry, laser scans, images and ground truth.

- `trajectory.csv`: t, odom_x, odom_y, odom_theta and optionally gt_x, gt_y, gt_theta (empty = unknown),
  image (site-relative path, empty = none), kidnapped (0/1: the robot was carried away before this step).
- `scans.npy`: float32 array [steps, laser.beams] of ranges in metres (NumPy format, loaded without pickle);
  a range >= laser.range_max or non-finite means no return.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import Problems, excerpt
from pipeline.io.captures import site_relative
from pipeline.io.map_yaml import OccupancyMap
from pipeline.io.site import Site
from pipeline.io.text_files import read_csv

REQUIRED = ("t", "odom_x", "odom_y", "odom_theta")
OPTIONAL = ("gt_x", "gt_y", "gt_theta", "image", "kidnapped")


@dataclass
class CaptureRun:
    name: str
    t: np.ndarray
    odom: np.ndarray  # (N, 3) odom_from_base
    gt: np.ndarray  # (N, 3) map_from_base, NaN where unknown
    ranges: np.ndarray  # (N, beams) float32
    image: list[str | None]
    kidnapped: list[bool | None]


def _parse_bool(text: str) -> bool | None:
    t = text.strip().lower()
    if t == "":
        return None
    if t in ("1", "true", "yes"):
        return True
    if t in ("0", "false", "no"):
        return False
    raise ValueError(f"kidnapped {text!r} is not 0/1")


def write_run(run_dir: Path, t, odom, gt, ranges, images, kidnapped) -> Path:
    """`trajectory.csv` + `scans.npy` of one run in this format, each file written atomically; a NaN
    ground-truth pose is written as empty (unknown), an image of None as no frame."""
    import io

    from pipeline.io.atomic import atomic_file, write_text_atomic

    run_dir = Path(run_dir)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*REQUIRED, *OPTIONAL])
    for i in range(len(t)):
        g = ["", "", ""] if np.isnan(gt[i][0]) else [repr(float(v)) for v in gt[i]]
        w.writerow([repr(float(t[i])), *(repr(float(v)) for v in odom[i]), *g, images[i] or "",
                    int(bool(kidnapped[i]))])
    with atomic_file(run_dir / "scans.npy", "wb") as fh:
        np.save(fh, np.asarray(ranges, dtype=np.float32), allow_pickle=False)
    write_text_atomic(run_dir / "trajectory.csv", buf.getvalue())
    return run_dir


def read_run(
    run_dir: Path, root: Path, site: Site | None, occ_map: OccupancyMap | None, problems: Problems
) -> CaptureRun | None:
    name = run_dir.name
    traj_path, scans_path = run_dir / "trajectory.csv", run_dir / "scans.npy"
    if not traj_path.is_file():
        problems.add(traj_path, "file is missing", fix="each run folder needs trajectory.csv and scans.npy")
        return None
    t, odom, gt, image, kidnapped, lines = [], [], [], [], [], []
    table = read_csv(traj_path, problems)
    if table is None:
        return None
    missing = [c for c in REQUIRED if c not in table.header]
    if missing:
        problems.add(traj_path, f"missing columns {missing} (found {excerpt(table.header, 200)})", row=1)
        return None
    for line, rec in table.rows:
        try:
            vals = [float(rec[c]) for c in REQUIRED]
            if not all(math.isfinite(v) for v in vals):
                raise ValueError("t and odometry must be finite")
            g = [rec.get(c, "") for c in ("gt_x", "gt_y", "gt_theta")]
            if all(v == "" for v in g):
                gvals = [math.nan] * 3
            elif any(v == "" for v in g):
                raise ValueError("gt_x, gt_y, gt_theta must be all given or all empty")
            else:
                gvals = [float(v) for v in g]
                if not all(math.isfinite(v) for v in gvals):
                    raise ValueError("ground truth must be finite or empty")
            kid = _parse_bool(rec.get("kidnapped", ""))
        except ValueError as exc:
            problems.add(traj_path, excerpt(exc, 120), row=line, fix="correct or remove this row")
            continue
        t.append(vals[0])
        odom.append(vals[1:])
        gt.append(gvals)
        img = rec.get("image", "") or None
        if img is not None:
            full = site_relative(root, img)
            if full is None or not full.is_file():
                problems.add(traj_path, f"image '{excerpt(img)}' does not exist inside the site", row=line)
        image.append(img)
        kidnapped.append(kid)
        lines.append(line)
    if not t:
        if not problems:
            problems.add(traj_path, "no rows", fix="a run needs at least one step")
        return None
    t_arr = np.array(t)
    back = np.nonzero(np.diff(t_arr) <= 0)[0]
    for i in back[:20]:
        problems.add(
            traj_path,
            f"t={t_arr[i + 1]} does not increase (previous {t_arr[i]})",
            row=lines[i + 1],
            fix="rows must be in time order with distinct times",
        )
    gt_arr = np.array(gt)
    if occ_map is not None:
        known = ~np.isnan(gt_arr[:, 0])
        vals = occ_map.value_at(gt_arr[known, 0], gt_arr[known, 1], outside=-2)
        for line, v in zip(np.array(lines)[known], vals, strict=True):
            if v == -2:
                problems.add(traj_path, "ground-truth pose is outside the map", row=int(line))
            elif v == 100:
                problems.add(traj_path, "ground-truth pose is inside a wall (occupied cell)", row=int(line))

    ranges = None
    if not scans_path.is_file():
        problems.add(scans_path, "file is missing", fix="save the scans with numpy.save as float32 [steps, beams]")
    else:
        try:
            ranges = np.load(scans_path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            problems.add(scans_path, f"not a readable NumPy array without pickle: {exc}")
        if ranges is not None:
            beams = site.laser.beams if site is not None else None
            if ranges.ndim != 2 or not np.issubdtype(ranges.dtype, np.floating):
                problems.add(scans_path, f"must be a 2-D float array [steps, beams], got {ranges.dtype} {ranges.shape}")
                ranges = None
            elif ranges.shape[0] != len(t):
                problems.add(
                    scans_path,
                    f"has {ranges.shape[0]} scans but trajectory.csv has {len(t)} valid rows",
                    fix="one scan per trajectory row",
                )
            elif beams is not None and ranges.shape[1] != beams:
                problems.add(scans_path, f"has {ranges.shape[1]} beams per scan, site.yaml laser.beams is {beams}")
            elif np.any(ranges[np.isfinite(ranges)] < 0):
                problems.add(scans_path, "has negative ranges")
    if ranges is None:
        return None
    return CaptureRun(name, t_arr, np.array(odom), gt_arr, ranges.astype(np.float32), image, kidnapped)
