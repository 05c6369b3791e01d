"""Stage `synth-laser`: a laser-only site (map, one long run, report) as `ingest-log` writes a real log.

The output is a dataset directory that `siteloc localize` replays like an ingested CARMEN log: map.yaml
+ map.pgm (what the mapping team has), runs/<name>.parquet (ground truth, synthesised odometry, scans
cast in the world, which also holds parked cars the map does not know), preview.png, report.json / .md
and preset.yaml (the effective preset). Same preset, same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError
from pipeline.io.atomic import atomic_dir, write_text_atomic
from pipeline.io.map_yaml import write_map
from pipeline.io.odometry import noise_json, relative_to_first, synthesise_odometry
from pipeline.io.tables import to_table, write_table
from pipeline.sitegen.campus import CampusPreset, drive, generate_campus

STAGE = "synth-laser"
#: Poses cast per batch (memory: batch x beams rays in flight).
CAST_BATCH = 64


def load_laser_preset(name_or_path: str | Path, overrides: dict | None = None) -> CampusPreset:
    """A laser-only preset by name (`configs/laser_sites/<name>.yaml`) or path, with dotted overrides."""
    from pipeline.config import CONFIG_DIR
    from pipeline.sitegen.presets import load_preset

    return load_preset(name_or_path, overrides, CampusPreset, CONFIG_DIR / "laser_sites")


def run_synth_laser(preset: CampusPreset, *, outputs: dict, force: bool = False, progress: bool = True) -> Path:
    """Generate the site and its run into `outputs["out"]`; returns the directory."""
    from pipeline.mapping.occupancy import endpoint_occupied_share
    from pipeline.mapping.preview import write_preview
    from pipeline.progress import progress_bar
    from pipeline.sitegen.laser import LaserScanner

    out = Path(outputs["out"])
    cells = preset.size[0] * preset.size[1] / preset.resolution**2
    if cells > 2e8:
        raise ConfigError(f"{preset.name}: {cells / 1e6:.0f} M cells at {preset.resolution} m; at most 200 M "
                          "(raise resolution or shrink size)")
    rng = np.random.default_rng(preset.seed + 1)
    campus = generate_campus(preset)
    gt = drive(campus, preset, rng)
    lz = preset.laser
    scanner = LaserScanner(campus.world, beams=lz.beams, fov_deg=lz.fov_deg, range_max=lz.range_max,
                           noise_sigma=lz.noise_sigma, dropout=lz.dropout, seed=preset.seed + 2)
    ranges = np.zeros((len(gt), lz.beams), np.float32)
    batches = range(0, len(gt), CAST_BATCH)
    for a in progress_bar(batches, desc="scanning", unit="batch", enabled=progress):
        ranges[a: a + CAST_BATCH] = scanner.cast_many(gt[a: a + CAST_BATCH])
    odom = synthesise_odometry(gt, preset.odometry_noise, preset.seed + 3)
    n = len(gt)
    columns = {"run": [preset.name] * n, "step": np.arange(n, dtype=np.int32),
               "t": np.arange(n, dtype=np.float64) * preset.scan_every_m,  # 1 m/s
               "odom_x": odom[:, 0], "odom_y": odom[:, 1], "odom_theta": odom[:, 2],
               "gt_x": gt[:, 0], "gt_y": gt[:, 1], "gt_theta": gt[:, 2], "ranges": list(ranges),
               "angle_min": np.full(n, scanner.angle_min, np.float32),
               "angle_increment": np.full(n, scanner.angle_increment, np.float32),
               "range_max": np.full(n, lz.range_max, np.float32), "image_id": [None] * n,
               "kidnapped": np.zeros(n, bool)}
    geometry = (scanner.angle_min, scanner.angle_increment, lz.range_max)
    report = _report(preset, campus, gt, odom, ranges, [
        endpoint_occupied_share(campus.map, gt, ranges, *geometry, tol) for tol in (0, 1)])
    with atomic_dir(out, force=force, inputs=()) as tmp:  # generated from the preset: no input to protect
        (tmp / "runs").mkdir()
        write_table(tmp / "runs" / f"{preset.name}.parquet", to_table("runs", columns), "runs",
                    metadata={"odometry": "synthesised", "odometry_noise": noise_json(preset.odometry_noise),
                              "odometry_seed": str(preset.seed + 3), "source": f"synth-laser {preset.name}",
                              "time_source": "step_index"})
        write_map(tmp / "map.yaml", campus.map)
        write_text_atomic(tmp / "report.json", json.dumps(report, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", _markdown(report))
        title = (f"{preset.name}: {n} scans x {lz.beams} beams, {report['path_length_m']:.0f} m drive, "
                 f"{campus.map.width}x{campus.map.height} cells @ {preset.resolution:g} m\n"
                 f"no return {report['no_return_share']:.0%}, odometry drift at end "
                 f"{report['odometry_drift_end_m']:.0f} m")
        write_preview(tmp / "preview.png", campus.map, gt, title)
        import yaml

        write_text_atomic(tmp / "preset.yaml", yaml.safe_dump(preset.model_dump(mode="json"), sort_keys=False))
    return out


def _report(preset: CampusPreset, campus, gt, odom, ranges, shares) -> dict:
    span = gt[:, :2].max(axis=0) - gt[:, :2].min(axis=0)
    drift = np.hypot(*(odom[:, :2] - relative_to_first(gt)[:, :2]).T)
    occ = campus.map
    kinds, counts = np.unique(campus.kinds, return_counts=True)
    return {
        "run": preset.name, "source": f"synth-laser {preset.name}", "scans": int(len(gt)),
        "beams": int(preset.laser.beams), "range_max_m": preset.laser.range_max,
        "no_return_share": round(float((ranges >= preset.laser.range_max).mean()), 4),
        "path_length_m": round(float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum()), 2),
        "scan_spacing_m": preset.scan_every_m,
        "trajectory_extent_m": [round(float(v), 2) for v in span],
        "map_size_cells": [occ.width, occ.height], "map_resolution_m": occ.resolution,
        "map_size_m": [round(occ.width * occ.resolution, 2), round(occ.height * occ.resolution, 2)],
        "map_cells_occupied_share": round(float(occ.occupied.mean()), 5),
        "map_cells_free_share": round(float(occ.free.mean()), 4),
        "blocks": {str(k): int(c) for k, c in zip(kinds, counts, strict=True)},
        "endpoint_on_occupied_share_tol0": round(shares[0], 4),
        "endpoint_on_occupied_share_tol1": round(shares[1], 4),
        "odometry": "synthesised", "odometry_noise": preset.odometry_noise.model_dump(mode="json"),
        "odometry_drift_end_m": round(float(drift[-1]), 3), "odometry_drift_max_m": round(float(drift.max()), 3),
    }


def _markdown(r: dict) -> str:
    rows = [("scans x beams", f"{r['scans']} x {r['beams']}, one every {r['scan_spacing_m']:g} m"),
            ("no-return readings", f"{100 * r['no_return_share']:.1f} % (beyond {r['range_max_m']:g} m)"),
            ("path length", f"{r['path_length_m']:.0f} m"),
            ("trajectory extent", "{} x {} m".format(*r["trajectory_extent_m"])),
            ("map size", "{} x {} cells = {} x {} m".format(*r["map_size_cells"], *r["map_size_m"])
             + f" at {r['map_resolution_m']:g} m"),
            ("blocks", ", ".join(f"{k} {v}" for k, v in r["blocks"].items())),
            ("endpoints on occupied cells", f"{r['endpoint_on_occupied_share_tol0']:.3f} exact, "
             f"{r['endpoint_on_occupied_share_tol1']:.3f} within 1 cell (parked cars are not in the map)"),
            ("odometry drift", f"{r['odometry_drift_end_m']:.1f} m at the end, {r['odometry_drift_max_m']:.1f} m "
             "at most")]
    lines = [f"# synth-laser: {r['run']}", "", "| quantity | value |", "| --- | --- |"]
    return "\n".join(lines + [f"| {k} | {v} |" for k, v in rows]) + "\n"
