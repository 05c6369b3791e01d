"""`captures.csv` of a site capture directory: one row per image of a 6-view capture stop.

Columns: image, stop_id, view, x, y, theta, room, area. `image` is the path relative to the site
root; x, y in metres and theta in radians are the map-frame pose of that view's camera
(`map_from_cam` heading = stop heading + the rig's yaw offset of `view`). See docs/capture-format.md.
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import Problems, excerpt
from pipeline.io.map_yaml import OccupancyMap
from pipeline.io.site import Site
from pipeline.io.text_files import read_csv
from pipeline.runtime.motion import wrap_angle

REQUIRED_COLUMNS = ("image", "stop_id", "view", "x", "y", "theta")
OPTIONAL_COLUMNS = ("room", "area")


@dataclass(frozen=True)
class CaptureRow:
    line: int
    image: str
    stop_id: str
    view: int
    x: float
    y: float
    theta: float
    room: str
    area: str


def site_relative(root: Path, rel: str) -> Path | None:
    """The file a site-relative path names, or None if it escapes the site root."""
    if not rel or Path(rel).is_absolute():
        return None
    full = (root / rel).resolve()
    try:
        full.relative_to(root.resolve())
    except ValueError:
        return None
    return full


def parse_pose(rec: dict[str, str], bad: list[str], cols=("x", "y", "theta")) -> dict[str, float]:
    """The finite numbers of a CSV row's pose columns; what is wrong with the others goes to `bad`."""
    nums = {}
    for col in cols:
        try:
            nums[col] = float(rec[col])
        except ValueError:
            bad.append(f"{col} '{excerpt(rec[col])}' is not a number")
            continue
        if not math.isfinite(nums[col]):
            bad.append(f"{col} is {rec[col]} (poses must be finite)")
    return nums


def read_captures(path: Path, problems: Problems, *, allow_empty: bool = False) -> list[CaptureRow]:
    """Parse captures.csv, reporting every unparsable row; returns the rows that parsed. `allow_empty`: a
    header alone is fine (a laser-only site, whose robot drove without a camera)."""
    if not path.is_file():
        problems.add(path, "file is missing", fix="list every image with its stop and pose (docs/capture-format.md)")
        return []
    rows: list[CaptureRow] = []
    table = read_csv(path, problems)
    if table is None:
        return []
    header = table.header
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        problems.add(
            path,
            f"missing columns {missing} (found {excerpt(header, 200)})",
            row=1,
            fix=f"the header must contain {', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)}",
        )
        return []
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        problems.warn(path, f"ignoring unknown columns {excerpt(unknown, 200)}", row=1)
    for line, rec in table.rows:
        bad = []
        try:
            view = int(rec["view"])
        except ValueError:
            bad.append(f"view '{excerpt(rec['view'])}' is not an integer")
            view = -1
        nums = parse_pose(rec, bad)
        if not rec["image"]:
            bad.append("image is empty")
        if not rec["stop_id"]:
            bad.append("stop_id is empty")
        if bad:
            problems.add(path, "; ".join(bad), row=line, fix="correct or remove this row")
            continue
        rows.append(
            CaptureRow(
                line,
                rec["image"],
                rec["stop_id"],
                view,
                nums["x"],
                nums["y"],
                nums["theta"],
                rec.get("room", ""),
                rec.get("area", ""),
            )
        )
    if not rows and not problems and not allow_empty:
        problems.add(path, "no capture rows", fix="a site needs at least one capture stop (or, for a laser-only "
                     "site, no camera section in site.yaml and runs/)")
    return rows


def check_rows(root: Path, csv_path: Path, rows: list[CaptureRow], problems: Problems) -> None:
    """Per-row path checks: inside the site root, existing, not listed twice."""
    first_line: dict[str, int] = {}
    for r in rows:
        if r.image in first_line:
            problems.add(
                csv_path,
                f"duplicate image id '{r.image}' (first on line {first_line[r.image]})",
                row=r.line,
                fix="list each image once",
            )
            continue
        first_line[r.image] = r.line
        full = site_relative(root, r.image)
        if full is None:
            problems.add(
                csv_path,
                f"image path '{r.image}' is absolute or leaves the site directory",
                row=r.line,
                fix="use a path relative to the site root, e.g. images/s000_v0.jpg",
            )
        elif not full.is_file():
            problems.add(
                csv_path, f"image '{r.image}' does not exist", row=r.line, fix="add the file or remove the row"
            )


def check_poses(csv_path: Path, rows: list[CaptureRow], occ_map: OccupancyMap, problems: Problems) -> None:
    """Every capture pose must be on the map and in free space."""
    if not rows:
        return
    xy = np.array([[r.x, r.y] for r in rows])
    row_idx, col_idx = occ_map.world_to_cell(xy[:, 0], xy[:, 1])
    inside = occ_map.contains(row_idx, col_idx)
    value = occ_map.value_at(xy[:, 0], xy[:, 1])
    for r, ins, val in zip(rows, inside, value, strict=True):
        if not ins:
            problems.add(
                csv_path,
                f"pose ({r.x:.2f}, {r.y:.2f}) of '{r.image}' is outside the map",
                row=r.line,
                fix="check the map origin/resolution or the pose's frame",
            )
        elif val == 100:
            problems.add(
                csv_path,
                f"pose ({r.x:.2f}, {r.y:.2f}) of '{r.image}' is inside a wall (occupied cell)",
                row=r.line,
                fix="check the pose or the map alignment",
            )
        elif val < 0:
            problems.warn(csv_path, f"pose ({r.x:.2f}, {r.y:.2f}) of '{r.image}' is on an unknown map cell", row=r.line)


def check_stops(
    csv_path: Path, rows: list[CaptureRow], site: Site, tol_m: float, tol_deg: float, problems: Problems
) -> None:
    """A stop is one rig placement: one row per rig view, one position, one base heading."""
    offsets = np.array(site.rig.yaw_offsets)
    n_views = len(offsets)
    by_stop: dict[str, list[CaptureRow]] = defaultdict(list)
    for r in rows:
        by_stop[r.stop_id].append(r)
    for stop, members in by_stop.items():
        first = members[0].line
        views = [m.view for m in members]
        if len(members) != n_views:
            problems.add(
                csv_path,
                f"stop '{stop}' has {len(members)} views, the rig has {n_views}",
                row=first,
                fix="every stop needs one image per rig view (site.yaml rig.yaw_offsets_deg)",
            )
        out_of_range = sorted({v for v in views if not 0 <= v < n_views})
        if out_of_range:
            problems.add(csv_path, f"stop '{stop}' has view numbers {out_of_range} outside 0..{n_views - 1}", row=first)
        dup = sorted({v for v in views if views.count(v) > 1})
        if dup:
            problems.add(csv_path, f"stop '{stop}' repeats views {dup}", row=first, fix="one row per view and stop")
        xy = np.array([[m.x, m.y] for m in members])
        spread = float(np.max(np.linalg.norm(xy - xy.mean(axis=0), axis=1)))
        if spread > tol_m:
            problems.add(
                csv_path,
                f"views of stop '{stop}' are {spread:.3f} m apart (tolerance {tol_m} m)",
                row=first,
                fix="all views of a stop share the rig position",
            )
        valid = [m for m in members if 0 <= m.view < n_views]
        if len(valid) >= 2:
            base = wrap_angle(np.array([m.theta for m in valid]) - offsets[[m.view for m in valid]])
            mean = math.atan2(np.sin(base).mean(), np.cos(base).mean())
            dev = float(np.degrees(np.max(np.abs(wrap_angle(base - mean)))))
            if dev > tol_deg:
                problems.add(
                    csv_path,
                    f"view headings of stop '{stop}' disagree with the rig yaw offsets by {dev:.1f} deg "
                    f"(tolerance {tol_deg} deg)",
                    row=first,
                    fix="theta is the camera heading in radians: stop heading + rig yaw offset of the view",
                )


def check_images(
    root: Path,
    csv_path: Path,
    rows: list[CaptureRow],
    site: Site | None,
    decode: bool,
    problems: Problems,
    progress: bool = True,
) -> dict[str, tuple[int, int, str]]:
    """Open every image (with `decode`, decode it whole: truncation shows only then); returns image -> (width,
    height, sha256) for the readable ones."""
    from pipeline.io.images import ImageError, image_size, open_image
    from pipeline.progress import progress_bar

    out: dict[str, tuple[int, int, str]] = {}
    for r in progress_bar(rows, desc="checking images", unit="img", enabled=progress, leave=False):
        full = site_relative(root, r.image)
        if full is None or not full.is_file() or r.image in out:
            continue
        data = full.read_bytes()
        digest = hashlib.sha256(data).hexdigest()
        try:
            w, h = open_image(data, name=r.image, rgb=False).size if decode else image_size(data, name=r.image)
        except ImageError as exc:  # collected: every bad image is reported at once
            problems.add(csv_path, f"image '{r.image}' is unreadable: {exc.message}", row=r.line, fix=exc.fix)
            continue
        if site is not None and site.camera is None:
            problems.add(csv_path, f"image '{r.image}' is listed, but site.yaml has no camera", row=r.line,
                         fix="add the camera's intrinsics (camera: width, height, fx, fy, cx, cy) to site.yaml")
        elif site is not None and (w, h) != (site.camera.width, site.camera.height):
            problems.add(
                csv_path,
                f"image '{r.image}' is {w}x{h}, site.yaml camera is {site.camera.width}x{site.camera.height}",
                row=r.line,
                fix="resize the image or correct camera.width/height in site.yaml",
            )
        out[r.image] = (w, h, digest)
    return out


def split_stops(stop_ids: list[str], test_fraction: float, seed: int) -> dict[str, str]:
    """Whole stops go to 'train' or 'test'; the same ids and seed always give the same split."""
    stops = sorted(set(stop_ids))
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(stops))
    n_test = int(round(test_fraction * len(stops)))
    if test_fraction > 0 and len(stops) > 1:
        n_test = min(max(n_test, 1), len(stops) - 1)
    test = {stops[i] for i in order[:n_test]}
    return {s: ("test" if s in test else "train") for s in stops}
