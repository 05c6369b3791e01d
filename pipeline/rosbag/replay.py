"""`siteloc localize --bag`: the runtime fed from a recording, and its estimates written back as ROS messages.

The recording becomes the dataset `localize` replays (map, site.yaml, one run of a step per scan with
the frame nearest in time: the same steps `ingest-bag` makes), in a temporary folder; the estimates
are `localize`'s own. With `write_bag`, trial 0 becomes a recording to watch in Foxglove or RViz
(`pipeline.rosbag.replay_bag`: the map, the scan, the particles, the estimate with its covariance,
map -> odom, the state and, with a bundle, the candidates and the camera frame), stamped with the
scans' own stamps so it plays alone or beside the recording.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import ConfigError, InputError, Problem
from pipeline.io.atomic import check_output, write_text_atomic
from pipeline.io.scan_rows import BLOCK_ROWS
from pipeline.rosbag.drive import (
    BagOptions,
    Drive,
    extract_drive,
    kept_frames,
    laser_of,
    map_of,
    notes_text,
    recording_notes,
    site_of,
)
from pipeline.rosbag.read import load_frames, read_recording
from pipeline.rosbag.replay_bag import write_replay_bag

#: Particles per step the replay recording shows (`/siteloc/particles`).
CLOUD = 200


def bag_dataset(bag: Path, root: Path, opts: BagOptions, cfg: SitelocConfig, map_yaml: Path | None = None,
                progress: bool = False) -> Drive:
    """Write the dataset of one recording under `root` (map.yaml, site.yaml, runs/<name>.parquet, images/)."""
    from pipeline.io import tables
    from pipeline.io.capture_runs import CaptureRun
    from pipeline.io.map_yaml import write_map
    from pipeline.io.site import Rig, write_site
    from pipeline.rosbag.bagfile import find_bags

    found = find_bags([bag])
    if len(found) != 1:
        raise InputError(f"{bag}: {len(found)} recordings", [Problem(str(bag), "localize --bag replays one recording",
                                                                      fix=f"pass one of {[p.name for p in found]}")])
    path = found[0]
    rec = read_recording(path, opts.roles, opts.offsets, opts.tf_max_gap_s, opts.sync_tolerance_s, progress)
    if rec.ranges is None:
        raise InputError(f"{path}: no laser scans", [Problem(str(path), "has no sensor_msgs/LaserScan topic",
                                                             fix="the filter needs the laser; record /scan")])
    drive = extract_drive(rec, Rig().yaw_offsets, opts, cfg.ingest.heading_tolerance_deg, use_stops=False)
    load_frames(rec, kept_frames(drive))
    site = site_of([rec], [drive], "".join(c if c.isalnum() or c in "_.-" else "_" for c in rec.name), opts)
    laser, _ = laser_of(rec, opts)
    write_map(root / "map.yaml", map_of([rec], map_yaml))
    write_site(root / "site.yaml", site)
    run = drive.run
    images: list[str | None] = []
    for k, fi in enumerate(run["image"]):
        if fi is None:
            images.append(None)
            continue
        _, _, data, fmt = rec.frames[fi]
        rel = f"images/{rec.name}/{k:04d}.{'jpg' if fmt == 'jpeg' else 'png'}"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
        images.append(rel)
    from pipeline.ingest import run_table

    def parts():  # a record batch of BLOCK_ROWS steps at a time: the ranges are read from the spool, never all held
        n = len(run["t"])
        for a in range(0, max(n, 1), BLOCK_ROWS):
            s = slice(a, a + BLOCK_ROWS)
            yield run_table(CaptureRun(rec.name, run["t"][s], run["odom"][s], run["gt"][s], run["ranges"][s],
                                       images[s], list(run["kidnapped"][s])), laser, site.name, first_step=a)

    # Arrow IPC, not Parquet: `localize` reads it a record batch at a time (`load_run`)
    tables.write_table_parts(root / "runs" / f"{rec.name}.arrow", parts(), "runs")
    return drive


def run_localize_bag(cfg: SitelocConfig, *, inputs: dict, outputs: dict[str, Path], options: BagOptions | None = None,
                     write_bag: Path | None = None, progress: bool = True, cloud: int = CLOUD,
                     live: dict | None = None, **localize_kw) -> Path:
    """`localize` on `inputs['bag']` (with `inputs['bundle']` for retrieval, `inputs['map']` for a map.yaml);
    optionally the replay as a recording to watch (`write_bag`: .mcap, or .bag for ROS 1). The replay
    recording goes through the output guard as `--out` does: never onto, into or around an input, never
    over an existing file without `force`; it is written inside the output and moved out when complete."""
    from pipeline.localize import run_localize

    opts = options or BagOptions()
    out = Path(outputs["out"])
    force = bool(localize_kw.get("force"))
    read = [v for v in inputs.values() if v is not None]
    inside = None
    if write_bag is not None:
        write_bag = Path(write_bag)
        if write_bag.suffix not in (".mcap", ".bag"):
            raise ConfigError(f"--write-bag {write_bag}: name a .mcap file (ROS 2, Foxglove) or a .bag file (ROS 1)")
        if write_bag.resolve() == out.resolve():
            raise ConfigError(f"--write-bag and --out name the same path ({out}): put the recording inside --out")
        check_output(write_bag, force=force, inputs=[*read, out] if not _within(write_bag, out) else read)
        if write_bag.is_dir():
            raise ConfigError(f"--write-bag {write_bag}: a folder is there; name a file")
        inside = write_bag.resolve().relative_to(out.resolve()) if _within(write_bag, out) else None
    with tempfile.TemporaryDirectory(prefix="siteloc-bag-") as tmp:
        drive = bag_dataset(Path(inputs["bag"]), Path(tmp), opts, cfg, inputs.get("map"), progress)
        staged = Path("replay" + (write_bag.suffix if write_bag is not None else ".mcap"))

        def on_replay(run, rep, work: Path) -> None:
            if write_bag is not None:
                (work / (inside or staged)).parent.mkdir(parents=True, exist_ok=True)
                write_replay_bag(work / (inside or staged), replay_stream(drive, rep, Path(tmp)))

        with contextlib.ExitStack() as stack:
            view = stack.enter_context(live_view(drive, Path(tmp), live)) if live is not None else None
            if view is not None:
                if live.get("on_start"):
                    live["on_start"](view.url)
                view.wait_for_client()
            result = run_localize(cfg, inputs={"data": Path(tmp)}, outputs=outputs, progress=progress,
                                  bundle=inputs.get("bundle"), keep_cloud=cloud if write_bag is not None else 0,
                                  on_replay=on_replay, on_step=None if view is None else
                                  lambda run, t, pose, state, parts, agree, spread: view.step(
                                      t, pose, state, parts, agree, spread), **localize_kw)
        notes = notes_text(recording_notes(drive))
        if notes:
            doc = json.loads((result / "metrics.json").read_text())
            doc["notes"] = notes + doc.get("notes", [])
            write_text_atomic(result / "metrics.json", json.dumps(doc, indent=2) + "\n")
    write_effective_config(cfg, result, stage="localize", inputs={k: v for k, v in inputs.items() if v is not None})
    if write_bag is not None and inside is None:
        write_bag.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(result / staged, write_bag.parent / f".{write_bag.name}.tmp")
        (write_bag.parent / f".{write_bag.name}.tmp").replace(write_bag)
    return result


def _recorded(drive: Drive, data: Path) -> dict:
    """What the replay recording and the live view show of the recording itself (the dataset `bag_dataset`
    wrote in `data`): stamps, map, odometry, the filter's scans and laser, frames. The scan is the filter's
    (levelled, on one beam grid) in frame `<laser>_2d` at the 2-D mount, never clashing with the recording's."""
    from pipeline.io.map_yaml import read_map
    from pipeline.io.site import read_site

    run, rec = drive.run, drive.rec
    laser = read_site(data / "site.yaml").laser
    f = drive.report["frames"]
    return {"stamps": run["t0"] + np.asarray(run["t"]), "map": read_map(data / "map.yaml"),
            "odom": np.asarray(run["odom"]), "ranges": run["ranges"],
            "angle_min": laser.angle_min, "angle_increment": laser.angle_increment,
            "base_from_laser": (laser.mount.x, laser.mount.y, np.radians(laser.mount.yaw_deg)),
            "frames": {"map": "map", "odom": f["odom"], "base": f["base"], "laser": f"{rec.laser_frame or 'laser'}_2d"},
            "range_min": float((rec.laser or {}).get("range_min", 0.0)), "range_max": laser.range_max}


def live_view(drive: Drive, data: Path, live: dict):
    """The `LiveView` of a recording's replay."""
    from pipeline.rosbag.live import LiveView

    r = _recorded(drive, data)
    return LiveView(r["map"], r["stamps"], r["odom"], r["ranges"], r["angle_min"], r["angle_increment"],
                    r["base_from_laser"], frames=r["frames"],
                    **{k: v for k, v in live.items() if k in ("host", "port", "speed", "wait_s")})


def _within(path: Path, folder: Path) -> bool:
    return Path(path).resolve().is_relative_to(Path(folder).resolve())


def replay_stream(drive: Drive, rep: dict, data: Path):
    """Trial 0 of a replay (`run_localize`'s `rep`, poses in the map frame) beside the recording's own scans,
    odometry, frames and map, as `write_replay_bag` takes them."""
    from pipeline.rosbag.replay_bag import ReplayStream

    run, rec, r = drive.run, drive.rec, _recorded(drive, data)
    frames = None
    if any(fi is not None for fi in run["image"]):
        frames = [None if fi is None else (rec.frames[fi][2], rec.frames[fi][3]) for fi in run["image"]]
    return ReplayStream(
        stamps=r["stamps"], map=r["map"], odom=r["odom"], base_from_laser=r["base_from_laser"], ranges=r["ranges"],
        angle_min=r["angle_min"], angle_increment=r["angle_increment"], range_min=r["range_min"],
        range_max=r["range_max"], pose=rep["pose"], cov=rep["cov"], state=list(rep["state"]),
        agreement=rep.get("agreement"), clouds=rep.get("cloud"), candidates=rep.get("candidates"), frames=frames,
        odom_frame=r["frames"]["odom"], base_frame=r["frames"]["base"], laser_frame=r["frames"]["laser"],
        camera_frame=rec.camera_frame or "camera")
