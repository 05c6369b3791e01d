"""Stage `export-bag`: a capture directory written as a robot would have recorded it, one bag per drive.

`capture` is the mapping session: the robot drives from stop to stop (shortest paths on the map) and at
each stop turns through the rig's headings, pausing 1 s at each view while the camera fires; its
odometry is synthesised with the filter's motion-model noise. Every run of `runs/` becomes a bag of its
own with its recorded odometry, scans and frames. Topics: /camera/image_raw/compressed,
/camera/camera_info (plumb_bob; D is site.yaml's distortion, else zero), /scan, /odom, /tf (odom ->
base_link from the odometry, map -> odom from the ground truth, as a localization system would publish
it), /tf_static and /map (latched). The odometry and tf run at 20 Hz (interpolated between a run's
steps); scans and frames at the run's own rate.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pipeline.config import OdometryNoise, SitelocConfig, write_effective_config
from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
from pipeline.rosbag.bagfile import BagWriter
from pipeline.rosbag.messages import CAMERA_INFO, COMPRESSED, GRID, ODOMETRY, SCAN, TF, yaw_quat
from pipeline.runtime.motion import compose2d, inverse2d, wrap_angle

START = 1_700_000_000.0  # bag clock of the first recording (an ordinary Unix time; fixed for reproducibility)
LATENCY = {"image": 0.030, "scan": 0.010, "odom": 0.002, "tf": 0.002}  # receive time after the stamp, s
ODOM_RATE = 20.0
CAPTURE_RATE = 10.0
FRAMES = {"map": "map", "odom": "odom", "base": "base_link", "laser": "laser", "camera": "camera_optical_frame"}
TOPICS = {"image": "/camera/image_raw/compressed", "camera_info": "/camera/camera_info", "scan": "/scan",
          "odom": "/odom", "tf": "/tf", "tf_static": "/tf_static", "map": "/map"}
# base_from_optical: the optical frame looks along the base's x axis (z forward, x right, y down).
OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def bag_path(out: Path, name: str, fmt: str) -> Path:
    return out / (f"{name}.bag" if fmt == "bag" else name)


def image_format(data: bytes, path: str) -> str:
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    raise ValueError(f"{path}: only JPEG and PNG images can go into a CompressedImage")


def _quat(matrix: np.ndarray) -> tuple[float, ...]:
    from scipy.spatial.transform import Rotation

    return tuple(Rotation.from_matrix(matrix).as_quat())


def interpolate_poses(t: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    """SE(2) poses at times `at`, linear in x, y and the unwrapped heading between samples."""
    th = np.unwrap(poses[:, 2])
    return np.column_stack([np.interp(at, t, poses[:, 0]), np.interp(at, t, poses[:, 1]),
                            wrap_angle(np.interp(at, t, th))])


def mounts(site, camera_height: float, laser_height: float) -> dict[str, tuple[tuple, tuple]]:
    """base_from_camera (optical frame) and base_from_laser as (xyz, quat): site.yaml's extrinsics when it
    has them (a site that came from a recording), else the camera at the base's centre looking along x
    at `camera_height` and the laser at its 2-D mount at `laser_height`."""
    ext = site.extrinsics
    m = site.laser.mount
    out = {"camera": ((0.0, 0.0, camera_height), _quat(OPTICAL)),
           "laser": ((m.x, m.y, laser_height), yaw_quat(math.radians(m.yaw_deg)))}
    if ext is not None and ext.base_from_camera is not None:
        out["camera"] = (ext.base_from_camera.xyz, ext.base_from_camera.quat_xyzw)
    if ext is not None and ext.base_from_laser is not None:
        out["laser"] = (ext.base_from_laser.xyz, ext.base_from_laser.quat_xyzw)
    return out


def camera_on_floor(site, camera_height: float) -> np.ndarray:
    """(1, 3) base_from_camera on the floor: the optical axis' heading and the camera's x, y on the base."""
    from scipy.spatial.transform import Rotation

    from pipeline.rosbag.transforms import Transforms

    xyz, quat = mounts(site, camera_height, 0.0)["camera"]
    return Transforms(Rotation.from_quat([quat]), np.array([xyz], float), np.ones(1, bool)).floor_pose(2)


def _static(w: BagWriter, stamp: float, site, camera_height: float, laser_height: float) -> None:
    msgs, m = w.msgs, mounts(site, camera_height, laser_height)
    w.write(TOPICS["tf_static"], stamp + LATENCY["tf"], msgs.tf([
        msgs.transform_stamped(stamp, FRAMES["base"], FRAMES["laser"], *m["laser"]),
        msgs.transform_stamped(stamp, FRAMES["base"], FRAMES["camera"], *m["camera"])]))


def _map(w: BagWriter, stamp: float, occ) -> None:
    msg = w.msgs.occupancy_grid(stamp, occ.grid, occ.resolution, (occ.origin_x, occ.origin_y, occ.origin_yaw))
    w.write(TOPICS["map"], stamp, msg)


def _odometry_and_tf(w: BagWriter, times: np.ndarray, odom: np.ndarray, map_times: np.ndarray,
                     map_from_odom: np.ndarray) -> None:
    msgs = w.msgs
    for i, (s, pose) in enumerate(zip(times, odom, strict=True)):
        w.write(TOPICS["odom"], s + LATENCY["odom"], msgs.odometry(s, pose, FRAMES["odom"], FRAMES["base"], seq=i))
        w.write(TOPICS["tf"], s + LATENCY["tf"], msgs.tf([msgs.transform_stamped(
            s, FRAMES["odom"], FRAMES["base"], (pose[0], pose[1], 0.0), yaw_quat(pose[2]))]))
    for s, pose in zip(map_times, map_from_odom, strict=True):
        w.write(TOPICS["tf"], s + LATENCY["tf"], msgs.tf([msgs.transform_stamped(
            s, FRAMES["map"], FRAMES["odom"], (pose[0], pose[1], 0.0), yaw_quat(pose[2]))]))


def _image(w: BagWriter, root: Path, rel: str, stamp: float, camera, seq: int) -> None:
    data = (root / rel).read_bytes()
    msgs = w.msgs
    w.write(TOPICS["image"], stamp + LATENCY["image"],
            msgs.compressed_image(stamp, FRAMES["camera"], data, image_format(data, rel), seq=seq))
    w.write(TOPICS["camera_info"], stamp + LATENCY["image"],
            msgs.camera_info(stamp, FRAMES["camera"], camera.width, camera.height, camera.fx, camera.fy, camera.cx,
                             camera.cy, seq=seq, d=None if camera.distortion is None else camera.distortion.coeffs))


def _topics(w: BagWriter, scans: bool) -> None:
    w.topic(TOPICS["tf_static"], TF, latched=True)
    w.topic(TOPICS["map"], GRID, latched=True)
    w.topic(TOPICS["tf"], TF)
    w.topic(TOPICS["odom"], ODOMETRY)
    w.topic(TOPICS["image"], COMPRESSED)
    w.topic(TOPICS["camera_info"], CAMERA_INFO)
    if scans:
        w.topic(TOPICS["scan"], SCAN)


def capture_session(v, camera_height: float = 1.2) -> tuple[np.ndarray, np.ndarray, list[tuple[float, str]]]:
    """Times (N,), map_from_base poses (N, 3) at CAPTURE_RATE and (stamp offset, image) of every view.

    The rows give map_from_cam; the base stands where that puts it through the camera's mount."""
    from pipeline.sitegen.routes import RoutePlanner

    dt = 1.0 / CAPTURE_RATE
    by_stop: dict[str, list] = {}
    for r in v.rows:
        by_stop.setdefault(r.stop_id, []).append(r)
    planner = RoutePlanner(v.occ_map, clearance=0.15)
    cam_from_base = inverse2d(camera_on_floor(v.site, camera_height))
    poses: list[np.ndarray] = []
    shots: list[tuple[int, str]] = []
    for stop_rows in by_stop.values():
        views = sorted(stop_rows, key=lambda r: r.view)
        base_of = {r.image: compose2d(np.array([[r.x, r.y, r.theta]]), cam_from_base)[0] for r in views}
        here = base_of[views[0].image]
        if poses:
            last = poses[-1]
            try:
                path = planner.leg((last[0], last[1]), (here[0], here[1]))
            except ValueError:  # a stop off the planner's clearance: drive straight
                path = np.array([last[:2], here[:2]])
            length = float(np.sum(np.hypot(*np.diff(path, axis=0).T)))
            if length > 1e-6:
                from pipeline.sitegen.routes import resample

                xy, direction = resample(path, 0.5 * dt)  # 0.5 m/s
                heading = np.unwrap(np.r_[last[2], direction])
                turn = np.linspace(heading[0], heading[1], max(2, int(abs(heading[1] - heading[0]) / 0.1)))
                poses += [np.array([last[0], last[1], h]) for h in turn[1:]]
                poses += [np.array([x, y, h]) for (x, y), h in zip(xy, direction, strict=True)]
        current = poses[-1] if poses else here
        for r in views:
            target = base_of[r.image]
            d = wrap_angle(target[2] - current[2])
            steps = max(2, int(math.ceil(abs(d) / math.radians(6.0))))  # 60 deg/s
            for f in np.linspace(0, 1, steps)[1:]:
                poses.append(np.array([current[0] + f * (target[0] - current[0]),
                                       current[1] + f * (target[1] - current[1]), current[2] + f * d]))
            hold = int(CAPTURE_RATE)
            for k in range(hold):
                poses.append(target.copy())
                if k == hold // 2:
                    shots.append((len(poses) - 1, r.image))
            current = target
    arr = np.array(poses)
    arr[:, 2] = wrap_angle(arr[:, 2])
    times = np.arange(len(arr)) * dt
    return times, arr, [(float(times[i]), img) for i, img in shots]


def write_capture_bag(path: Path, v, fmt: str, start: float, seed: int, camera_height: float,
                      laser_height: float) -> dict:
    from pipeline.io.odometry import synthesise_odometry

    times, gt, shots = capture_session(v, camera_height)
    odom = synthesise_odometry(gt, OdometryNoise(), seed)
    with BagWriter(path, fmt) as w:
        _topics(w, scans=False)
        _static(w, start, v.site, camera_height, laser_height)
        _map(w, start, v.occ_map)
        _odometry_and_tf(w, start + times, odom, start + times, compose2d(gt, inverse2d(odom)))
        for seq, (t, img) in enumerate(shots):
            _image(w, v.root, img, start + t, v.site.camera, seq)
        counts = dict(w.counts)
    return {"duration_s": float(times[-1]), "messages": counts}


def write_run_bag(path: Path, v, run, fmt: str, start: float, camera_height: float, laser_height: float) -> dict:
    t = run.t - run.t[0]
    grid = np.arange(0.0, t[-1] + 1e-9, 1.0 / ODOM_RATE)
    times = np.unique(np.round(np.r_[grid, t], 6))
    odom = interpolate_poses(t, run.odom, times)
    known = ~np.isnan(run.gt[:, 0])
    map_from_odom = compose2d(run.gt[known], inverse2d(run.odom[known]))
    laser = v.site.laser
    scan_time = float(np.median(np.diff(t))) if len(t) > 1 else 0.1
    with BagWriter(path, fmt) as w:
        _topics(w, scans=True)
        _static(w, start, v.site, camera_height, laser_height)
        _map(w, start, v.occ_map)
        _odometry_and_tf(w, start + times, odom, start + t[known], map_from_odom)
        for k, s in enumerate(start + t):
            w.write(TOPICS["scan"], s + LATENCY["scan"], w.msgs.scan(
                s, FRAMES["laser"], run.ranges[k], laser.angle_min, laser.angle_increment, laser.range_max,
                scan_time, seq=k))
            if run.image[k]:
                _image(w, v.root, run.image[k], s, v.site.camera, k)
        counts = dict(w.counts)
    return {"duration_s": float(t[-1]), "messages": counts}


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def run_export_bag(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], fmt: str = "mcap",
                   camera_height: float = 1.2, laser_height: float = 0.3, seed: int = 0,
                   force: bool = False, progress: bool = True) -> Path:
    """Write `inputs['site']` (a capture directory) into `outputs['out']`: capture + one bag per run, report."""
    from pipeline.ingest import validate_site_dir
    from pipeline.progress import progress_bar

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    v = validate_site_dir(inputs["site"], cfg.ingest, progress=progress)
    report: dict = {"site": v.site.name, "format": fmt, "bags": {}}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        jobs = [("capture", None)] + [(run.name, run) for run in v.runs]
        for i, (name, run) in enumerate(progress_bar(jobs, desc="writing bags", unit="bag", enabled=progress)):
            path = bag_path(tmp, name, fmt)
            start = START + 3600.0 * i
            if run is None:
                info = write_capture_bag(path, v, fmt, start, seed, camera_height, laser_height)
            else:
                info = write_run_bag(path, v, run, fmt, start, camera_height, laser_height)
            info["bytes"] = _size(path)
            info["path"] = path.name
            report["bags"][name] = info
        write_text_atomic(tmp / "export_report.json", json.dumps(report, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="export_bag", inputs=inputs)
    return out
