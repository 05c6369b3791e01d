"""`siteloc localize --bag`: the runtime fed from a recording, and its estimates written back as ROS messages.

The recording becomes the dataset `localize` replays (map, site.yaml, one run of a step per scan with
the frame nearest in time: the same steps `ingest-bag` makes), in a temporary folder; the estimates
are `localize`'s own. `write_estimates_bag` writes them as a robot's localization would publish
them: geometry_msgs/PoseWithCovarianceStamped on /siteloc/pose and the map -> odom transform on /tf,
stamped with the scans' own stamps so they play beside the recording.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.rosbag.ingest import BagOptions, Drive, extract_drive, kept_frames, laser_of, map_of, site_of
from pipeline.rosbag.read import load_frames, read_recording

POSE_TOPIC = "/siteloc/pose"


def bag_dataset(bag: Path, root: Path, opts: BagOptions, cfg: SitelocConfig, map_yaml: Path | None = None) -> Drive:
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
    rec = read_recording(path, opts.roles, opts.offsets, opts.tf_max_gap_s, opts.sync_tolerance_s)
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
    capture = CaptureRun(rec.name, run["t"], run["odom"], run["gt"], np.asarray(run["ranges"], np.float32), images,
                         list(run["kidnapped"]))
    from pipeline.ingest import run_table

    tables.write_table(root / "runs" / f"{rec.name}.parquet", run_table(capture, laser, site.name), "runs")
    return drive


def run_localize_bag(cfg: SitelocConfig, *, inputs: dict, outputs: dict[str, Path], options: BagOptions | None = None,
                     write_bag: Path | None = None, progress: bool = True, **localize_kw) -> Path:
    """`localize` on `inputs['bag']` (with `inputs['bundle']` for retrieval); optionally the estimates as a bag."""
    from pipeline.localize import run_localize

    opts = options or BagOptions()
    if write_bag is not None and Path(write_bag).exists() and not localize_kw.get("force"):
        from pipeline.errors import OutputExistsError

        raise OutputExistsError(Path(write_bag))
    with tempfile.TemporaryDirectory(prefix="siteloc-bag-") as tmp:
        drive = bag_dataset(Path(inputs["bag"]), Path(tmp), opts, cfg, inputs.get("map"))
        out = run_localize(cfg, inputs={"data": Path(tmp)}, outputs=outputs, progress=progress,
                           bundle=inputs.get("bundle"), **localize_kw)
    write_effective_config(cfg, out, stage="localize", inputs={k: v for k, v in inputs.items() if v is not None})
    if write_bag is not None:
        write_estimates_bag(out / "estimates.parquet", drive, Path(write_bag), force=bool(localize_kw.get("force")))
    return out


def write_estimates_bag(estimates: Path, drive: Drive, dst: Path, force: bool = False) -> Path:
    """Trial 0's estimates as /siteloc/pose and map -> odom on /tf; `.bag` is ROS 1, else mcap."""
    from pipeline.io import tables
    from pipeline.rosbag.bagfile import BagWriter
    from pipeline.rosbag.messages import POSE_COV, TF, yaw_quat
    from pipeline.rosbag.transforms import compose2d, inverse2d

    est = tables.read_table(estimates, "estimates").to_pydict()
    trial0 = [i for i, tr in enumerate(est["trial"]) if tr == 0]
    pose = np.array([[est["x"][i], est["y"][i], est["theta"][i]] for i in trial0])
    cov = np.array([[[est["cov_xx"][i], est["cov_xy"][i], 0.0], [est["cov_xy"][i], est["cov_yy"][i], 0.0],
                     [0.0, 0.0, est["cov_tt"][i]]] for i in trial0])
    run = drive.run
    stamps = run["t0"] + np.asarray(run["t"])
    map_from_odom = compose2d(pose, inverse2d(np.asarray(run["odom"])))
    fmt = "bag" if dst.suffix == ".bag" else "mcap"
    odom_frame = drive.rec.odom_frame or "odom"
    if dst.exists() and not force:
        from pipeline.errors import OutputExistsError

        raise OutputExistsError(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    try:
        inner = work / ("out.bag" if fmt == "bag" else "out")
        with BagWriter(inner, fmt) as w:
            w.topic(POSE_TOPIC, POSE_COV)
            w.topic("/tf", TF)
            for k, s in enumerate(stamps):
                w.write(POSE_TOPIC, s, w.msgs.pose_with_covariance(s, pose[k], cov[k], "map", seq=k))
                m = map_from_odom[k]
                w.write("/tf", s, w.msgs.tf([w.msgs.transform_stamped(s, "map", odom_frame, (m[0], m[1], 0.0),
                                                                      yaw_quat(m[2]))]))
        made = inner if fmt == "bag" else next(inner.glob("*.mcap"))  # a bare .mcap file, as Foxglove opens
        if dst.exists():
            shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
        made.replace(dst)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return dst
