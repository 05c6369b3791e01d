"""`siteloc ingest-log`: a CARMEN laser log -> runs table, occupancy map, preview and report."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Ingest a CARMEN 2D-laser log with a corrected trajectory: build its occupancy map and a runs table.

Reads FLASER and ROBOTLASER1 messages from a .log or .log.gz file; ODOM, NEFF, PARAM, comments and other
message types are counted and ignored. The pose in each laser line is the SLAM-corrected one and serves
as ground truth.

FLASER beams follow the SICK conventions: the scan starts at -90 deg, counter-clockwise; an even beam
count n steps 180/n deg (180 -> 1 deg, 360 -> 0.5 deg), an odd one spans -90..+90 deg inclusive (181,
361). Readings equal to a no-return code (ingest_log.laser.no_return_ranges: 81.83, 81.91, 50.0) or
above ingest_log.laser.range_max are stored as range_max: in the runs table a range >= range_max means
"no return".

Writes into --out, atomically (nothing is left behind if it fails):
  runs/<run>.parquet  per scan: ground-truth pose, noisy odometry, ranges
  map.yaml, map.pgm   occupancy map (ROS map_server) from the corrected poses
  preview.png         the map with the trajectory, to check by eye
  report.json, .md    scans, beams, map size, endpoints on occupied cells
  config.yaml         the effective configuration

The odometry is synthesised from the ground truth with the motion-model noise ingest_log.odometry_noise
and seed ingest_log.seed, so the same inputs give identical outputs. A malformed line stops the
command, naming its line number; --skip-bad-lines skips and counts such lines instead.

--every-m 1.0 keeps one scan per metre of travel in the runs table (a robot that scans less often, or
moves fast: the hard case for a particle filter); the map is still built from every scan.

Example: siteloc ingest-log ../shared/data/carmen/intel-corrected.log.gz --out data/intel/ingested
"""

LogArg = Annotated[
    Path,
    typer.Argument(
        help="CARMEN log (.log or .log.gz), e.g. ../shared/data/carmen/intel-corrected.log.gz.",
        show_default=False,
    ),
]
OutOpt = Annotated[
    Path,
    typer.Option("--out", "-o", help="Output directory (must not exist unless --force).", show_default=False),
]
SkipOpt = Annotated[
    bool,
    typer.Option("--skip-bad-lines", help="Skip malformed lines (counted in the report) instead of failing."),
]


def ingest_log(
    log: LogArg,
    out: OutOpt,
    config: ConfigOpt = "demo",
    set_: set_opt("ingest_log.mapping.resolution=0.1") = None,
    skip_bad_lines: SkipOpt = False,
    every_m: Annotated[float | None, typer.Option(
        "--every-m", min=0.0, help="Keep one scan per this many metres travelled (ingest_log.scan_every_m; "
        "0: every scan).", show_default=False)] = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.ingest_log import run_ingest_log

        cfg = load(config, set_)
        if every_m is not None:
            cfg = cfg.model_copy(update={"ingest_log": cfg.ingest_log.model_copy(update={"scan_every_m": every_m})})
        result = run_ingest_log(
            cfg,
            inputs={"log": log},
            outputs={"out": out},
            force=force,
            skip_bad_lines=skip_bad_lines,
            progress=sys.stderr.isatty(),
        )
        report = json.loads((result / "report.json").read_text())
        typer.echo(
            f"{report['run']}: {report['scans']} scans x {report['beams']} beams, map "
            "{} x {} cells ({} x {} m), ".format(*report["map_size_cells"], *report["map_size_m"])
            + f"endpoints on occupied cells {report['endpoint_on_occupied_share_tol0']:.3f} "
            f"(within 1 cell {report['endpoint_on_occupied_share_tol1']:.3f})"
        )
        if report["skipped_lines"]:
            typer.echo(f"skipped {report['skipped_lines']} malformed line(s); see report.md")
        echo_path("output", result)
