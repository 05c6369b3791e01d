"""`siteloc ingest-bag` and `siteloc export-bag`: ROS 1 / ROS 2 / mcap recordings in and out."""

from __future__ import annotations

import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, print_tables, set_opt

INGEST_HELP = """Turn robot recordings (ROS 1 .bag, ROS 2 bag folders with sqlite3 or mcap storage, bare .mcap /
.db3 files) into a site capture directory that `siteloc ingest` takes unchanged.

Each BAG is one drive (a folder of bags gives all of them). Topics are found by message type:
sensor_msgs Image / CompressedImage with CameraInfo (intrinsics), LaserScan, nav_msgs Odometry,
/tf and /tf_static (map -> odom -> base_link -> camera / laser), nav_msgs OccupancyGrid (or --map).
--list prints what each recording holds; --topic camera=/front/image_raw picks a topic by role
(camera, camera_info, scan, odom, map).

Capture stops: where the robot stands and turns through 360 degrees, the 6 views 60 degrees apart are
the frames nearest to those headings (the paper's capture). --stops every --stops-every 2.0 takes a
stop every 2 m of a continuous drive instead, each view the frame within 1 m nearest to its heading:
a weaker capture (views from different places, headings only as driven); the report says which
--set the ingest then needs. Turns and places without every view are listed in the report.

Every recording with laser scans becomes runs/<bag name>/: a step per scan, the odometry and the
reference pose (map -> base_link) interpolated from tf at the scan's stamp, the camera frame nearest in
time (--sync-tolerance), kidnapped where the reference jumps against the odometry. A sensor whose
clock is off by a known amount is corrected with --time-offset camera=-0.12.

Writes into --out: site.yaml (intrinsics, laser, tf_static's 3-D extrinsics), map.yaml + map.pgm,
captures.csv + images/ (stopNNNN_vK.jpg in time order: label these for annotations.json), runs/,
bag_report.json + bag_report.md (what was dropped and why: stamps without a pose, duplicate stamps,
tf gaps, silences of the laser) and config.yaml. --annotations brings a COCO file's boxes along, its
images matched to the stop images by file name or else by their bytes.

Example: siteloc ingest-bag recordings/ --out data/mysite/site --map maps/floor3.yaml
"""

EXPORT_HELP = """Write a site capture directory as a robot would have recorded it: one bag per drive.

capture is the mapping session (the robot drives from stop to stop along shortest paths on the map and
turns through the rig's headings, pausing 1 s per view while the camera fires); every run of runs/
becomes a bag of its own. Topics: /camera/image_raw/compressed, /camera/camera_info, /scan, /odom,
/tf (odom -> base_link; map -> odom from the ground truth), /tf_static, /map. Odometry and tf at 20 Hz,
scans and frames at the run's own rate, stamps from a fixed clock (reproducible).

--format mcap (default) and db3 write ROS 2 bag folders (open the .mcap in Foxglove), bag a ROS 1 file.
`siteloc ingest-bag` reads them back. Writes export_report.json (messages and bytes per bag).

Example: siteloc export-bag data/reference/site --out data/reference/bags --format mcap
"""


class Format(StrEnum):
    mcap = "mcap"
    db3 = "db3"
    bag = "bag"


class StopsMode(StrEnum):
    turns = "turns"
    every = "every"


def pairs(values: list[str] | None, what: str, number: bool = False) -> dict:
    from pipeline.errors import ConfigError

    out = {}
    for v in values or []:
        key, sep, val = v.partition("=")
        if not sep or not key or not val:
            raise ConfigError(f"{what} '{v}' must be ROLE=VALUE, e.g. camera=/camera/image_raw")
        if number:
            try:
                out[key] = float(val)
            except ValueError:
                raise ConfigError(f"{what} '{v}': '{val}' is not a number of seconds") from None
        else:
            out[key] = val
    return out


def topic_roles(topic: list[str] | None) -> dict[str, str]:
    """--topic ROLE=TOPIC pairs, every role one siteloc knows (`pipeline.rosbag.read.ROLES`)."""
    from pipeline.errors import ConfigError
    from pipeline.rosbag.read import ROLES

    roles = pairs(topic, "--topic")
    bad = [r for r in roles if r not in ROLES]
    if bad:
        raise ConfigError(f"--topic roles {bad} unknown; roles are {list(ROLES)}")
    return roles


def _print_inventory(paths: list[Path]) -> None:
    from rich.table import Table

    from pipeline.rosbag.bagfile import find_bags
    from pipeline.rosbag.inventory import inventory

    for p in find_bags(paths):
        inv = inventory(p)
        t = Table(title=f"{inv['name']}: {inv['storage']}, {inv['duration_s']:.1f} s, {inv['messages']} messages")
        for col in ("topic", "type", "count", "rate (Hz)", "siteloc role"):
            t.add_column(col)
        for topic, i in inv["topics"].items():
            t.add_row(topic, i["type"], str(i["count"]), "-" if i["rate_hz"] is None else f"{i['rate_hz']:.1f}",
                      i["role"] or "-")
        print_tables(t, min_width=110)


def ingest_bag(
    bags: Annotated[list[Path], typer.Argument(help="Recordings, or folders of them.", show_default=False)],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output capture directory.",
                                             show_default=False)] = None,
    list_: Annotated[bool, typer.Option("--list", help="Print what the recordings hold and stop.")] = False,
    topic: Annotated[list[str] | None, typer.Option("--topic", help="ROLE=TOPIC, e.g. camera=/front/image_raw "
                                                    "(repeatable).")] = None,
    frame: Annotated[list[str] | None, typer.Option("--frame", help="ROLE=FRAME for map, odom, base, e.g. "
                                                    "base=base_footprint (repeatable).")] = None,
    time_offset: Annotated[list[str] | None, typer.Option("--time-offset", help="ROLE=SECONDS added to a "
                                                          "sensor's stamps, e.g. camera=-0.12 (repeatable).")] = None,
    map_yaml: Annotated[Path | None, typer.Option("--map", help="map.yaml to use instead of the /map topic.",
                                                  show_default=False)] = None,
    annotations: Annotated[Path | None, typer.Option("--annotations", help="COCO boxes for the stop images.",
                                                     show_default=False)] = None,
    stops: Annotated[StopsMode, typer.Option("--stops", help="turns: 360-degree turns in place; every: a stop "
                                             "every --stops-every metres.")] = StopsMode.turns,
    stops_every: Annotated[float, typer.Option("--stops-every", min=0.1, help="Stop spacing for --stops every, "
                                               "m.")] = 2.0,
    stops_from: Annotated[list[str] | None, typer.Option("--stops-from", help="Take stops only from this "
                                                         "recording (repeatable) \\[default: all].")] = None,
    stop_radius: Annotated[float, typer.Option(help="A turn in place stays within this, m.")] = 0.05,
    view_tolerance: Annotated[float | None, typer.Option(help="A view's frame within this of its heading, deg "
                                                         "\\[default: ingest.heading_tolerance_deg; 15 for every].",
                                                         show_default=False)] = None,
    sync_tolerance: Annotated[float, typer.Option(help="A frame goes with a scan within this, s.")] = 0.05,
    tf_max_gap: Annotated[float, typer.Option(help="tf is interpolated across at most this, s.")] = 0.5,
    kidnap_jump: Annotated[float, typer.Option(help="Reference jump against the odometry that flags a "
                                               "kidnapping, m.")] = 1.0,
    scan_stride: Annotated[int, typer.Option(min=1, help="Keep every Nth scan as a run step.")] = 1,
    name: Annotated[str | None, typer.Option(help="Site name \\[default: the output folder's].",
                                             show_default=False)] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("ingest.heading_tolerance_deg=5") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        if list_:
            _print_inventory(bags)
            return
        from pipeline.errors import ConfigError

        if out is None:
            raise ConfigError("--out is required (or --list to only look)")
        import json

        from pipeline.rosbag.drive import notes_text
        from pipeline.rosbag.ingest import BagOptions, run_ingest_bag

        opts = BagOptions(roles=topic_roles(topic), offsets=pairs(time_offset, "--time-offset", number=True),
                          frames=pairs(frame, "--frame"), stops=StopsMode(stops).value, stops_every_m=stops_every,
                          stops_from=list(stops_from or []), stop_radius_m=stop_radius,
                          view_tolerance_deg=view_tolerance, sync_tolerance_s=sync_tolerance, tf_max_gap_s=tf_max_gap,
                          kidnap_jump_m=kidnap_jump, scan_stride=scan_stride, name=name)
        cfg = load(config, set_)
        path = run_ingest_bag(cfg, inputs={"bags": bags, "map": map_yaml, "annotations": annotations},
                              outputs={"out": out}, options=opts, force=force, progress=sys.stderr.isatty())
        rep = json.loads((path / "bag_report.json").read_text())
        typer.echo(f"ingested {len(rep['recordings'])} recordings: {rep['stops']} stops, {len(rep['runs'])} runs, "
                   f"{rep['messages']} messages at {rep['messages_per_s']:.0f} msg/s")
        for n, r in rep["recordings"].items():
            drop = {k: v for k, v in r["dropped"].items() if isinstance(v, int) and v and k != "sync_tolerance_s"}
            gaps = r["dropped"].get("tf_gaps", [])
            if r["incomplete_stops"] or drop or gaps:
                typer.secho(f"{n}: {len(r['incomplete_stops'])} incomplete stops, dropped {drop or 'nothing'}, "
                            f"{len(gaps)} tf gaps (see bag_report.md)", fg=typer.colors.YELLOW, err=True)
            for note in notes_text(r):
                typer.echo(f"{n}: {note}", err=True)
        if rep["ingest_needs"]:
            typer.secho(f"the stops are a weaker capture: run `siteloc ingest` with {rep['ingest_needs']}",
                        fg=typer.colors.YELLOW, err=True)
        echo_path("output", path)


def export_bag(
    site_dir: Annotated[Path, typer.Argument(help="Site capture directory (holds site.yaml).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder of bags.", show_default=False)],
    fmt: Annotated[Format, typer.Option("--format", help="mcap, db3 (ROS 2) or bag (ROS 1).")] = Format.mcap,
    camera_height: Annotated[float, typer.Option(help="Camera above the floor when site.yaml has no extrinsics, "
                                                 "m.")] = 1.2,
    laser_height: Annotated[float, typer.Option(help="Laser above the floor when site.yaml has no extrinsics, "
                                                "m.")] = 0.3,
    seed: Annotated[int, typer.Option(help="Seed of the capture session's odometry noise.")] = 0,
    config: ConfigOpt = "demo",
    set_: set_opt("ingest.decode_images=false") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.rosbag.export import run_export_bag

        cfg = load(config, set_)
        path = run_export_bag(cfg, inputs={"site": site_dir}, outputs={"out": out}, fmt=Format(fmt).value,
                              camera_height=camera_height, laser_height=laser_height, seed=seed, force=force,
                              progress=sys.stderr.isatty())
        rep = json.loads((path / "export_report.json").read_text())
        for n, b in rep["bags"].items():
            typer.echo(f"{n}: {sum(b['messages'].values())} messages, {b['duration_s']:.1f} s, "
                       f"{b['bytes'] / 1e6:.1f} MB -> {path / b['path']}")
        echo_path("output", path)
