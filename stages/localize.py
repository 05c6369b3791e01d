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
  pose        at a known pose (tracking): --pose X,Y,THETA (metres, metres, degrees, in the map frame:
              what nav2's "2D Pose Estimate" sets), else the first ground-truth pose
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

Writes into --out: estimates.parquet (per step: pose, covariance, state, particles, the share of beams the
map explains at the estimate and the particle spread, error where there is ground truth), metrics.json
(converged step, the steps where it lost track, share of steps within 0.5 m after convergence, median /
mean / p90 error after convergence and median over all steps, recovery steps per kidnapping, particles,
ms per update, evo's APE / RPE; a summary over trials), trajectories/ (estimates and ground truth as TUM
files, for `evo_ape tum trajectories/RUN_groundtruth.tum trajectories/RUN_trial0.tum`), plots/ (error
and particles per step, the trajectory and particles on the map, error CDF) and config.yaml. A trial
counts as converged when the error settled under 0.5 m for 10 steps and never afterwards stayed at
0.5 m or more for 10 steps (kidnappings aside); one that did is reported as "lost track at" that step.
Without ground truth (a robot's own recording) the verdict is what the robot can know: converged when
for 20 steps at least 80 % of the beams end within 0.15 m of a wall of the map, the particles' spread
stays under 0.5 m and the filter is tracking, and lost when that fails for 20 steps afterwards
(docs/localize-your-recording.md); plots/RUN_overview.png shows each run on the map, coloured by state.

--bag replays one ROS recording (ROS 1 .bag, ROS 2 folder, .mcap / .db3) as the robot would feed the runtime:
a step per scan with the odometry (odom -> base in /tf, else /odom), and, as ground truth when tf has it,
map -> base_link at the scan's stamp, and the camera frame nearest in time (what `siteloc ingest-bag` makes
of it). A laser-only recording with no map frame (what a robot records) works: --map gives the map.
--write-bag OUT.mcap (or .bag for ROS 1) writes the replay to watch in Foxglove or RViz: the map, the scan,
the particles, the estimate with its covariance, map -> odom, the filter's state and, with --bundle, the
retrieved candidates and the camera frame, stamped like the scans. --live serves the replay to Foxglove
as it runs (Open connection > Foxglove WebSocket > ws://127.0.0.1:8765), at the recording's speed.

Example: siteloc localize data/carmen/intel-corrected --out data/localize/intel --init uniform --trials 10

Example: siteloc localize --bag take2 --map map.yaml --init pose --pose 2.5,4.0,90 --out out/take2
--write-bag out/take2/replay.mcap
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
    topic: Annotated[list[str] | None, typer.Option("--topic", help="With --bag: ROLE=TOPIC where a recording has "
                                                    "several, e.g. scan=/scan_front (repeatable).",
                                                    show_default=False)] = None,
    frame: Annotated[list[str] | None, typer.Option("--frame", help="With --bag: ROLE=FRAME for map, odom, base, "
                                                    "e.g. base=base_footprint (repeatable).",
                                                    show_default=False)] = None,
    live: Annotated[bool, typer.Option("--live", help="With --bag: serve the replay to Foxglove as it runs (a "
                                       "WebSocket server on 127.0.0.1; needs the foxglove-sdk package).")] = False,
    live_port: Annotated[int, typer.Option("--live-port", min=0, max=65535, help="Port of --live (0: any free).")]
    = 8765,
    live_speed: Annotated[float, typer.Option("--live-speed", min=0.0, help="With --live: replay at this many "
                                              "times the recording's speed (0: as fast as it runs).")] = 1.0,
    live_wait: Annotated[float, typer.Option("--live-wait", min=0.0, help="With --live: wait up to this many "
                                             "seconds for Foxglove to subscribe before the first step.")] = 0.0,
    bag_map: Annotated[Path | None, typer.Option("--map", help="With --bag: map.yaml when the recording has no "
                                                 "/map.", show_default=False)] = None,
    run: Annotated[
        list[str] | None, typer.Option("--run", "-r", help="Replay only this run (repeatable) \\[default: all].")
    ] = None,
    init: Annotated[Init, typer.Option("--init", help="How the filter starts (see above).")] = Init.uniform,
    pose: Annotated[str | None, typer.Option("--pose", help="With --init pose: X,Y,THETA (m, m, degrees) in the map "
                                             "frame.", show_default=False)] = None,
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
        start = _pose(pose) if pose is not None else None
        if start is not None and init != Init.pose.value:
            raise ConfigError("--pose goes with --init pose")
        cfg = load(config, set_)
        kw = dict(init=init, trials=trials, kidnap_at=kidnap_at, kidnap_min_jump_m=kidnap_min_jump, force=force,
                  start_pose=start)
        if (topic or frame or live) and bag is None:
            raise ConfigError("--topic, --frame and --live go with --bag")
        if bag is not None:
            from pipeline.rosbag.drive import BagOptions
            from pipeline.rosbag.replay import run_localize_bag
            from stages.bag import pairs, topic_roles

            opts = BagOptions(roles=topic_roles(topic), frames=pairs(frame, "--frame"))
            view = None if not live else {
                "port": live_port, "speed": live_speed, "wait_s": live_wait,
                "on_start": lambda url: typer.echo(f"live view: {url} (Foxglove: Open connection > Foxglove "
                                                   "WebSocket)", err=True)}
            result = run_localize_bag(cfg, inputs={"bag": bag, "bundle": bundle, "map": bag_map},
                                      outputs={"out": out}, options=opts, write_bag=write_bag,
                                      progress=sys.stderr.isatty(), live=view, **kw)
        else:
            result = run_localize(cfg, inputs={"data": data}, outputs={"out": out}, runs=run, bundle=bundle,
                                  progress=sys.stderr.isatty(), **kw)
        doc = json.loads((result / "metrics.json").read_text())
        from rich.table import Table

        table = Table(title=f"siteloc localize: init {init}, {doc['method']}, {doc['sensor_model']}",
                      caption="converged: settled within 0.5 m and never lost track afterwards; lost track: "
                              "settled, then 0.5 m or more for 10 steps (kidnappings aside). No reference: "
                              "converged when 80 % of the beams meet the map, spread < 0.5 m, tracking, for 20 steps")
        for col in ("run", "converged", "lost track at", "conv. step", "within 0.5 m", "median err (m)",
                    "median err, all (m)", "APE rmse, evo (m)", "kidnaps recovered", "recovery steps", "ms/update"):
            table.add_column(col)
        for name, s in doc["summary"].items():
            if "converged" not in s:
                q = doc["runs"][name][0]["quality"]
                conv = "yes" if q["converged"] else "lost" if q["lost_steps"] else "no"
                table.add_row(name, f"{conv} (no reference)", ", ".join(map(str, q["lost_steps"])) or "-",
                              "-" if q["converged_step"] is None else str(q["converged_step"]), "-", "-", "-", "-",
                              "-", "-", "-" if s.get("update_ms_mean") is None else f"{s['update_ms_mean']:.1f}")
                continue

            def f(v, fmt="{:.3f}"):
                return "-" if v is None else fmt.format(v)

            lost = "; ".join(", ".join(map(str, steps)) for steps in s["lost_track_steps"] if steps) or "-"
            table.add_row(name, f"{s['converged']}/{s['trials']}", lost, f(s["converged_step_median"], "{:.0f}"),
                          f(s["within_threshold_share_median"], "{:.0%}"), f(s["error_median_m"]),
                          f(s["error_median_all_m"]), f(s["ape_rmse_m_median"]), f"{s['recovered']}/{s['kidnaps']}",
                          f(s["recovery_steps_median"], "{:.0f}"), f(s["update_ms_mean"], "{:.1f}"))
        print_tables(table, min_width=150)
        for note in doc.get("notes", []):
            typer.echo(f"note: {note}", err=True)
        echo_path("output", result)


def _pose(text: str) -> tuple[float, float, float]:
    """--pose X,Y,THETA (m, m, degrees) as x, y, theta (radians)."""
    import math

    from pipeline.errors import ConfigError

    parts = text.replace(" ", "").split(",")
    try:
        x, y, th = (float(v) for v in parts)
    except ValueError:
        raise ConfigError(f"--pose {text!r}: expected X,Y,THETA (metres, metres, degrees), e.g. --pose 2.5,4.0,90") \
            from None
    if not all(math.isfinite(v) for v in (x, y, th)):
        raise ConfigError(f"--pose {text!r}: X, Y and THETA must be finite numbers")
    return x, y, math.radians(th)
