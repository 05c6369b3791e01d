"""`run_ingest_log`: a CARMEN laser log -> runs table, occupancy map, preview and report.

The corrected logs give the ground-truth trajectory only, so the map is built with known poses from
it, and the odometry a localizer will see is synthesised from the ground truth with seeded noise.
Everything is written into a temporary directory that replaces `out` only when complete, and the
outputs hold no timestamps: the same log, config and seed give byte-identical files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io.atomic import atomic_dir, write_text_atomic
from pipeline.io.carmen import CarmenLog, read_carmen
from pipeline.io.map_yaml import OccupancyMap, write_map
from pipeline.io.odometry import noise_json, relative_to_first, synthesise_odometry
from pipeline.io.tables import to_table, write_table
from pipeline.mapping.occupancy import (
    MAX_MAP_CELLS,
    MapTooLargeError,
    build_occupancy_map,
    endpoint_occupied_share,
    max_side_m,
    valid_returns,
)
from pipeline.mapping.preview import write_preview

STAGE = "ingest-log"
#: A log with fewer usable returns than this share of its readings is refused: its map would be (nearly)
#: all unknown. The real logs have 96-99 %; a log of NaN or no-return codes only has 0.
MIN_VALID_SHARE = 0.01
#: Far poses listed one by one when a map is too large.
MAX_FAR_LISTED = 10


def run_name(log_path: Path) -> str:
    """`intel-corrected.log.gz` -> `intel-corrected`: the file name without `.gz` and `.log`."""
    name = Path(log_path).name
    for suffix in (".gz", ".log"):
        if name.endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return name


def _runs_table(run: str, log: CarmenLog, odom: np.ndarray):
    n = log.n_scans
    columns = {
        "run": [run] * n,
        "step": np.arange(n, dtype=np.int32),
        "t": log.t,
        "odom_x": odom[:, 0],
        "odom_y": odom[:, 1],
        "odom_theta": odom[:, 2],
        "gt_x": log.poses[:, 0],
        "gt_y": log.poses[:, 1],
        "gt_theta": log.poses[:, 2],
        "ranges": list(log.ranges),
        "angle_min": np.full(n, log.angle_min, dtype=np.float32),
        "angle_increment": np.full(n, log.angle_increment, dtype=np.float32),
        "range_max": np.full(n, log.range_max, dtype=np.float32),
        "image_id": [None] * n,
        "kidnapped": np.zeros(n, dtype=bool),
    }
    return to_table("runs", columns)


def every_metre(poses: np.ndarray, step_m: float) -> np.ndarray:
    """Indices of the scans kept when one is kept per `step_m` of travel: the first, then each one at least
    `step_m` (path length along the ground truth) past the last kept one. `step_m` 0 keeps every scan."""
    if step_m <= 0 or len(poses) == 0:
        return np.arange(len(poses))
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    keep, last = [0], 0.0
    for i in range(1, len(poses)):
        if travelled[i] - last >= step_m:
            keep.append(i)
            last = travelled[i]
    return np.asarray(keep)


def subsample(log: CarmenLog, keep: np.ndarray) -> CarmenLog:
    """The log with only the scans `keep` (the replayed run of a robot scanning less often)."""
    from dataclasses import replace

    return replace(log, t=log.t[keep], poses=log.poses[keep], ranges=log.ranges[keep],
                   line_numbers=log.line_numbers[keep],
                   no_return_count=int((log.ranges[keep] >= log.range_max).sum()))


def _r(value: float, digits: int = 4) -> float:
    return round(float(value), digits)


def build_report(
    run: str,
    log: CarmenLog,
    odom: np.ndarray,
    occ_map: OccupancyMap,
    shares: tuple[float, float],
    cfg: SitelocConfig,
) -> dict:
    """The numbers a person checks after ingesting a log (also the source of report.md)."""
    xy = log.poses[:, :2]
    span = xy.max(axis=0) - xy.min(axis=0)
    gt_rel = relative_to_first(log.poses)
    drift = float(np.hypot(*(odom[-1, :2] - gt_rel[-1, :2])))
    res = occ_map.resolution
    return {
        "run": run,
        "source": log.path.name,
        "scans": log.n_scans,
        "beams": log.n_beams,
        "angle_min_deg": _r(np.degrees(log.angle_min)),
        "angle_increment_deg": _r(np.degrees(log.angle_increment), 6),
        "range_max_m": _r(log.range_max),
        "no_return_share": _r(log.no_return_count / log.ranges.size),
        "time_source": log.time_source,
        "path_length_m": _r(np.hypot(*np.diff(xy, axis=0).T).sum(), 2),
        "trajectory_extent_m": [_r(span[0], 2), _r(span[1], 2)],
        "map_size_cells": [occ_map.width, occ_map.height],
        "map_size_m": [_r(occ_map.width * res, 2), _r(occ_map.height * res, 2)],
        "map_resolution_m": res,
        "map_origin": [occ_map.origin_x, occ_map.origin_y, occ_map.origin_yaw],
        "map_cells_occupied_share": _r(occ_map.occupied.mean()),
        "map_cells_free_share": _r(occ_map.free.mean()),
        "endpoint_on_occupied_share_tol0": _r(shares[0]),
        "endpoint_on_occupied_share_tol1": _r(shares[1]),
        "odometry": "synthesised",
        "odometry_seed": cfg.ingest_log.seed,
        "odometry_noise": cfg.ingest_log.odometry_noise.model_dump(mode="json"),
        "odometry_drift_end_m": _r(drift, 3),
        "skipped_lines": log.skipped_lines,
        "skipped_line_problems": [f"line {p.row}: {p.message}" for p in log.skipped],
        "message_counts": log.message_counts,
        "unknown_message_types": log.unknown_messages,
    }


def report_markdown(report: dict) -> str:
    rows = [
        ("source", report["source"]),
        ("scans x beams", f"{report['scans']} x {report['beams']}"
         + (f" (one per {report['scan_every_m']:g} m of the log's {report['scans_in_log']})"
            if report.get("scan_every_m") else "")),
        ("beam angles", f"{report['angle_min_deg']:g} deg + i * {report['angle_increment_deg']:g} deg"),
        (
            "no-return readings",
            f"{100 * report['no_return_share']:.1f} % (stored as range_max = {report['range_max_m']:g} m)",
        ),
        ("time source", report["time_source"]),
        ("path length", f"{report['path_length_m']:.1f} m"),
        ("trajectory extent", "{} x {} m".format(*report["trajectory_extent_m"])),
        (
            "map size",
            "{} x {} cells = {} x {} m".format(*report["map_size_cells"], *report["map_size_m"])
            + f" at {report['map_resolution_m']:g} m",
        ),
        (
            "endpoints on occupied cells",
            f"{report['endpoint_on_occupied_share_tol0']:.3f} exact, "
            f"{report['endpoint_on_occupied_share_tol1']:.3f} within 1 cell",
        ),
        (
            "odometry",
            f"synthesised, seed {report['odometry_seed']}, drift at end {report['odometry_drift_end_m']:.2f} m",
        ),
        ("skipped malformed lines", str(report["skipped_lines"])),
        ("messages", ", ".join(f"{k} {v}" for k, v in report["message_counts"].items())),
    ]
    lines = [f"# ingest-log: {report['run']}", "", "| quantity | value |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in rows]
    if report["skipped_line_problems"]:
        lines += ["", "## Skipped lines", ""] + [f"- {p}" for p in report["skipped_line_problems"]]
    return "\n".join(lines) + "\n"


def check_returns(log_path: Path, log: CarmenLog, max_range_m: float) -> None:
    """Refuse a log whose readings are (almost) all invalid: it would map to an all-unknown grid."""
    valid = int(valid_returns(log.ranges, log.range_max, max_range_m).sum())
    total = int(log.ranges.size)
    if valid >= MIN_VALID_SHARE * total and valid > 0:
        return
    reach = min(log.range_max, max_range_m)
    raise InputError(
        f"{log_path}: " + ("no valid ranges found" if valid == 0 else "too few valid ranges")
        + f", {valid} of {total} readings ({valid / total:.1%}); a map needs at least {MIN_VALID_SHARE:.0%}",
        [
            Problem(
                str(log_path),
                f"a valid range is a finite reading between 0 and {reach:g} m; NaN, inf, 0, the no-return codes "
                f"and readings >= ingest_log.laser.range_max ({log.range_max:g} m) are not",
                fix="check the log's range fields (a corrupt export or a laser that saw nothing), or raise "
                "ingest_log.mapping.max_range_m / ingest_log.laser.range_max if its returns are longer",
            )
        ],
    )


def too_large_error(log_path: Path, log: CarmenLog, exc: MapTooLargeError, max_range_m: float) -> InputError:
    """The InputError for a map over MAX_MAP_CELLS, naming the lines of the poses far from the trajectory."""
    xy = log.poses[:, :2]
    centre = np.median(xy, axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        dist = np.hypot(*(xy - centre).T)
    side = max_side_m(exc.resolution)
    # Far: outside the largest map around the median and 10x further out than the typical pose (not a big site).
    far = np.nonzero(~(dist <= max(side / 2, 10 * float(np.median(dist)))))[0]
    far = far[np.argsort(-np.nan_to_num(dist[far], nan=np.inf), kind="stable")]
    summary = f"{log_path}: {exc}"
    if len(far) == 0:
        span = np.ptp(xy, axis=0)
        return InputError(summary, [Problem(
            str(log_path),
            f"the trajectory spans {span[0]:.0f} x {span[1]:.0f} m and the beams reach up to "
            f"{min(log.range_max, max_range_m):g} m beyond it",
            fix="map at a coarser resolution (--set ingest_log.mapping.resolution=0.1), lower "
            "ingest_log.mapping.max_range_m, or split the log into parts of one building each",
        )])
    if len(far) > MAX_FAR_LISTED:
        summary += f"; {len(far)} poses lie far from the rest, the first {MAX_FAR_LISTED} listed"
    fix = (f"correct or delete this line: a pose that far from the rest of the trajectory is corrupt (a map spans "
           f"at most {MAX_MAP_CELLS:,} cells, {side:.4g} x {side:.4g} m at {exc.resolution:g} m)")
    return InputError(summary, [
        Problem(str(log_path),
                f"pose ({log.poses[i, 0]:.6g}, {log.poses[i, 1]:.6g}) lies {dist[i]:.3g} m from the median "
                f"position of the trajectory ({centre[0]:.2f}, {centre[1]:.2f})",
                row=int(log.line_numbers[i]), fix=fix)
        for i in far[:MAX_FAR_LISTED]
    ])


def run_ingest_log(
    cfg: SitelocConfig,
    *,
    inputs: dict,
    outputs: dict,
    force: bool = False,
    skip_bad_lines: bool = False,
    progress: bool = True,
) -> Path:
    """Ingest `inputs["log"]` into `outputs["out"]`; returns the output directory.

    Writes runs/<run>.parquet, map.yaml + map.pgm, preview.png, report.json + report.md, config.yaml.
    `progress` shows a tqdm bar while mapping. Raises `InputError` for a missing or malformed log, one with
    (almost) no valid ranges, or one whose map would exceed MAX_MAP_CELLS (naming the lines of far poses),
    and `OutputExistsError` if `out` exists without `force`; `out` is untouched on any failure.
    """
    log_path, out = Path(inputs["log"]), Path(outputs["out"])
    if not log_path.is_file():
        raise InputError(
            f"{log_path}: CARMEN log not found",
            [
                Problem(
                    str(log_path),
                    "file is missing",
                    fix="give the path of a .log or .log.gz file, e.g. ../shared/data/carmen/intel-corrected.log.gz",
                )
            ],
        )
    section = cfg.ingest_log
    run = run_name(log_path)
    with atomic_dir(out, force=force, inputs=[log_path]) as tmp:
        full = read_carmen(log_path, section.laser, skip_bad_lines=skip_bad_lines)
        check_returns(log_path, full, section.mapping.max_range_m)
        geometry = (full.angle_min, full.angle_increment, full.range_max)
        # The map a mapping team would have: from every scan, however sparsely the runs table keeps them.
        try:
            occ_map = build_occupancy_map(full.poses, full.ranges, *geometry, section.mapping, progress=progress)
        except MapTooLargeError as exc:
            raise too_large_error(log_path, full, exc, section.mapping.max_range_m) from None
        if not occ_map.occupied.any():
            raise InputError(f"{log_path}: no valid ranges found: the map has no occupied cell", [Problem(
                str(log_path), "every return was cleared again by other beams (the map would be free and unknown "
                "cells only)", fix="check the log's poses and ranges; a map needs walls to localize against")])
        log = subsample(full, every_metre(full.poses, section.scan_every_m))
        odom = synthesise_odometry(log.poses, section.odometry_noise, section.seed)
        (tmp / "runs").mkdir()
        write_table(
            tmp / "runs" / f"{run}.parquet",
            _runs_table(run, log, odom),
            "runs",
            metadata={
                "odometry": "synthesised",
                "odometry_noise": noise_json(section.odometry_noise),
                "odometry_seed": str(section.seed),
                "source": log_path.name,
                "time_source": log.time_source,
            },
        )
        write_map(tmp / "map.yaml", occ_map)
        shares = tuple(
            endpoint_occupied_share(
                occ_map, log.poses, log.ranges, *geometry, tol, max_range=section.mapping.max_range_m
            )
            for tol in (0, 1)
        )
        report = build_report(run, log, odom, occ_map, shares, cfg)
        report["scans_in_log"] = full.n_scans
        report["scan_every_m"] = section.scan_every_m
        write_text_atomic(tmp / "report.json", json.dumps(report, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", report_markdown(report))
        title = (
            f"{run}: {log.n_scans} scans x {log.n_beams} beams, {report['path_length_m']:.0f} m path, "
            f"{occ_map.width}x{occ_map.height} cells @ {occ_map.resolution:g} m\n"
            f"endpoints on occupied cells: {shares[0]:.3f} (exact), {shares[1]:.3f} (within 1 cell)"
        )
        write_preview(tmp / "preview.png", occ_map, log.poses, title)
        write_effective_config(cfg, tmp, stage=STAGE, inputs={"log": log_path})
    return out
