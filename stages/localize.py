"""`siteloc localize`: replay runs through the runtime filter and measure it."""

from __future__ import annotations

import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, print_tables, set_opt

HELP = """Replay recorded runs through the runtime filter (adaptive MCL on the laser map) and measure it.

DATA is a directory written by `siteloc ingest` or `siteloc ingest-log`: map.yaml plus runs/<run>.parquet
(odometry, scans, ground truth when known). Each run is replayed --trials times (trial t uses seed
filter.seed + t). The filter starts as --init says:

  uniform     global localization: particles over the whole free space
  pose        at the first ground-truth pose (tracking)
  candidates  a simulated camera: at every step four ranked poses, the true pose with 0.5 m / 10 deg
              noise among random free-space decoys at a random rank, handed to the runtime's camera
              path as retrieval's would be (seed, inject while not tracking, weigh against a tracked
              belief; docs/runtime.md)
  retrieval   the deployable bundle given by --bundle (`siteloc export`), as the robot runs it: the
              runs' camera frames go through retrieval and the same camera path; the filter settings
              are the bundle's (filter.yaml)

--kidnap-at 300 --kidnap-at 700 teleports the robot at those steps to a far part of the run while its
odometry carries on unaware; runs that already flag kidnappings (the reference site's query runs) keep them.

The filter's settings are the `filter` section of the config: method (amcl, kld, mcl, mixture),
particles, sensor model (likelihood_field or beam), kidnap rule. Override them with --set, e.g.
--set filter.sensor.model=beam --set filter.max_particles=10000.

Writes into --out: estimates.parquet (per step: pose, covariance, state, particles, error), metrics.json
(converged step, the steps where it lost track, share of steps within 0.5 m after convergence, median /
mean / p90 error after convergence and median over all steps, recovery steps per kidnapping, particles,
ms per update, evo's APE / RPE; a summary over trials), trajectories/ (estimates and ground truth as TUM
files, for `evo_ape tum trajectories/RUN_groundtruth.tum trajectories/RUN_trial0.tum`), plots/ (error
and particles per step, the trajectory and particles on the map, error CDF) and config.yaml. A trial
counts as converged when the error settled under 0.5 m for 10 steps and never afterwards stayed at
0.5 m or more for 10 steps (kidnappings aside); one that did is reported as "lost track at" that step.

--bag replays one ROS recording (ROS 1 .bag, ROS 2 folder, .mcap / .db3) as the robot would feed the runtime:
a step per scan with the odometry and, as ground truth when tf has it, map -> base_link at the scan's
stamp, and the camera frame nearest in time (what `siteloc ingest-bag` makes of it). --write-bag OUT.mcap
writes the estimates as geometry_msgs/PoseWithCovarianceStamped on /siteloc/pose and the map -> odom
transform on /tf, stamped like the scans, to play beside the recording in RViz or Foxglove.

Example: siteloc localize data/carmen/intel-corrected --out data/localize/intel --init uniform --trials 10

Example: siteloc localize --bag bags/query_00 --bundle bundles/office-v1 --out data/localize/bag
--write-bag data/localize/bag/poses.mcap
"""


class Init(StrEnum):
    """How the filter starts (pipeline.localize.INITS)."""

    uniform = "uniform"
    pose = "pose"
    candidates = "candidates"
    retrieval = "retrieval"


def localize(
    data: Annotated[Path | None, typer.Argument(help="Dataset directory (map.yaml + runs/); not with --bag.",
                                                show_default=False)] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output directory.", show_default=False)] = None,
    bag: Annotated[Path | None, typer.Option("--bag", help="Replay one ROS recording instead of DATA (see above).",
                                             show_default=False)] = None,
    write_bag: Annotated[Path | None, typer.Option("--write-bag", help="With --bag: write the estimates to this "
                                                   "recording (.mcap, or .bag for ROS 1).", show_default=False)] = None,
    bag_map: Annotated[Path | None, typer.Option("--map", help="With --bag: map.yaml when the recording has no "
                                                 "/map.", show_default=False)] = None,
    run: Annotated[
        list[str] | None, typer.Option("--run", "-r", help="Replay only this run (repeatable) \\[default: all].")
    ] = None,
    init: Annotated[Init, typer.Option("--init", help="How the filter starts (see above).")] = Init.uniform,
    trials: Annotated[int, typer.Option("--trials", min=1, help="Replays per run, with seeds seed..seed+N-1.")] = 1,
    kidnap_at: Annotated[
        list[int] | None, typer.Option("--kidnap-at", help="Teleport the robot at this step (repeatable).")
    ] = None,
    kidnap_min_jump: Annotated[float, typer.Option(help="A teleport moves at least this far, m.")] = 10.0,
    bundle: Annotated[
        Path | None, typer.Option("--bundle", "-b", help="A bundle from `siteloc export` (implies --init retrieval).")
    ] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("filter.max_particles=10000") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.localize import run_localize

        if bundle is not None and init == Init.uniform:
            init = Init.retrieval
        init = Init(init).value  # the pipeline takes a plain string
        from pipeline.errors import ConfigError

        if out is None:
            raise ConfigError("--out is required")
        if (data is None) == (bag is None):
            raise ConfigError("give either DATA (a dataset directory) or --bag (a recording), not both or neither")
        if write_bag is not None and bag is None:
            raise ConfigError("--write-bag goes with --bag")
        cfg = load(config, set_)
        kw = dict(init=init, trials=trials, kidnap_at=kidnap_at, kidnap_min_jump_m=kidnap_min_jump, force=force)
        if bag is not None:
            from pipeline.rosbag.replay import run_localize_bag

            result = run_localize_bag(cfg, inputs={"bag": bag, "bundle": bundle, "map": bag_map},
                                      outputs={"out": out}, write_bag=write_bag, progress=sys.stderr.isatty(), **kw)
        else:
            result = run_localize(cfg, inputs={"data": data}, outputs={"out": out}, runs=run, bundle=bundle,
                                  progress=sys.stderr.isatty(), **kw)
        doc = json.loads((result / "metrics.json").read_text())
        from rich.table import Table

        table = Table(title=f"siteloc localize: init {init}, {doc['method']}, {doc['sensor_model']}",
                      caption="converged: settled within 0.5 m and never lost track afterwards; lost track: "
                              "settled, then 0.5 m or more for 10 steps (kidnappings aside)")
        for col in ("run", "converged", "lost track at", "conv. step", "within 0.5 m", "median err (m)",
                    "median err, all (m)", "APE rmse, evo (m)", "kidnaps recovered", "recovery steps", "ms/update"):
            table.add_column(col)
        for name, s in doc["summary"].items():
            if "converged" not in s:
                table.add_row(name, *["-"] * 10)
                continue

            def f(v, fmt="{:.3f}"):
                return "-" if v is None else fmt.format(v)

            lost = "; ".join(", ".join(map(str, steps)) for steps in s["lost_track_steps"] if steps) or "-"
            table.add_row(name, f"{s['converged']}/{s['trials']}", lost, f(s["converged_step_median"], "{:.0f}"),
                          f(s["within_threshold_share_median"], "{:.0%}"), f(s["error_median_m"]),
                          f(s["error_median_all_m"]), f(s["ape_rmse_m_median"]), f"{s['recovered']}/{s['kidnaps']}",
                          f(s["recovery_steps_median"], "{:.0f}"), f(s["update_ms_mean"], "{:.1f}"))
        print_tables(table, min_width=150)
        echo_path("output", result)
