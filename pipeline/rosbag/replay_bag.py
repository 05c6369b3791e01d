"""A localization replay as one recording: what RViz / Foxglove show of the filter, step by step.

`write_replay_bag` writes a `ReplayStream` (plain arrays, one row per scan the filter took) as a ROS 1
`.bag` or a bare `.mcap` of ROS 2 messages, stamped with the scans' own header stamps, so the file plays
on its own or beside the recording it came from. Topics (`TOPICS`):

    /map                        nav_msgs/OccupancyGrid               latched, once, at the first stamp
    /tf_static                  tf2_msgs/TFMessage                   latched, once: base -> laser
    /tf                         tf2_msgs/TFMessage                   per step: map -> odom and odom -> base
    /siteloc/scan               sensor_msgs/LaserScan                per step, in the laser frame
    /siteloc/pose               geometry_msgs/PoseWithCovarianceStamped  per step (x, y, yaw of the 6x6)
    /siteloc/particles          geometry_msgs/PoseArray              the steps with a particle subset
    /siteloc/state              std_msgs/String                      the first step and where it changes
    /siteloc/agreement          std_msgs/Float32                     per step with a finite value, if given
    /siteloc/candidates         geometry_msgs/PoseArray              the steps with candidates, if given
    /siteloc/camera/compressed  sensor_msgs/CompressedImage          the steps with a frame, if given

Messages go to the file in time order as they are made (`BagWriter(ordered=True)`): a 40 Hz drive of
20 minutes holds no more than one step in memory besides the stream itself. The file is written under a
temporary folder beside `dst` and renamed onto `dst` when complete; a failure leaves `dst` as it was.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.map_yaml import OccupancyMap
from pipeline.io.scan_rows import ScanRows

TOPICS = {
    "map": "/map",
    "tf_static": "/tf_static",
    "tf": "/tf",
    "scan": "/siteloc/scan",
    "pose": "/siteloc/pose",
    "particles": "/siteloc/particles",
    "state": "/siteloc/state",
    "agreement": "/siteloc/agreement",
    "candidates": "/siteloc/candidates",
    "camera": "/siteloc/camera/compressed",
}
STATES = ("tracking", "relocalising", "lost")
FRAME_FORMATS = ("jpeg", "png")


@dataclass(frozen=True, eq=False, kw_only=True)
class ReplayStream:
    """One replay, step by step (radians, metres, float seconds); T steps, B beams. Arrays are checked and
    converted on construction (stamps, odom, pose, cov float64; ranges float32)."""

    stamps: np.ndarray  # (T,) the scans' header stamps, non-decreasing
    map: OccupancyMap
    odom: np.ndarray  # (T, 3) odom_from_base
    base_from_laser: tuple[float, float, float]  # x, y, yaw of the laser on the base
    ranges: np.ndarray | ScanRows  # (T, B)
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    pose: np.ndarray  # (T, 3) map_from_base, the estimate
    cov: np.ndarray  # (T, 3, 3) of x, y, yaw
    state: list[str]  # (T,) tracking | relocalising | lost
    agreement: np.ndarray | None = None  # (T,) share of beams the map explains; NaN: none that step
    clouds: list[np.ndarray | None] | None = None  # (T,) of (K_t, 3) particle subsets x, y, theta
    candidates: list[np.ndarray | None] | None = None  # (T,) of (k, 4) x, y, theta, weight
    frames: list[tuple[bytes, str] | None] | None = None  # (T,) of (bytes, "jpeg" | "png")
    map_frame: str = "map"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    laser_frame: str = "laser"
    camera_frame: str = "camera"

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        n = len(stamps)
        if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0):
            raise ValueError("stamps must be finite and non-decreasing (the scans' header stamps in order)")
        put("stamps", stamps)
        for name, shape, dtype in (("odom", (n, 3), np.float64), ("pose", (n, 3), np.float64),
                                   ("cov", (n, 3, 3), np.float64)):
            arr = np.asarray(getattr(self, name), dtype=dtype)
            if arr.shape != shape:
                raise ValueError(f"{name} has shape {arr.shape}, expected {shape} ({n} steps)")
            put(name, arr)
        # rows read from disk a block at a time (a long recording's) stay so; the writer reads one row a step
        ranges = self.ranges if isinstance(self.ranges, ScanRows) else np.asarray(self.ranges, dtype=np.float32)
        if len(ranges.shape) != 2 or ranges.shape[0] != n:
            raise ValueError(f"ranges has shape {ranges.shape}, expected ({n}, beams)")
        put("ranges", ranges)
        mount = tuple(float(v) for v in self.base_from_laser)
        if len(mount) != 3:
            raise ValueError(f"base_from_laser must be (x, y, yaw), got {self.base_from_laser!r}")
        put("base_from_laser", mount)
        if not isinstance(self.map, OccupancyMap):
            raise ValueError(f"map must be an OccupancyMap, got {type(self.map).__name__}")
        state = [str(s) for s in self.state]
        if len(state) != n:
            raise ValueError(f"state has {len(state)} entries, expected {n}")
        unknown = sorted(set(state) - set(STATES))
        if unknown:
            raise ValueError(f"unknown states {unknown}; known: {list(STATES)}")
        put("state", state)
        if self.agreement is not None:
            agreement = np.asarray(self.agreement, dtype=np.float64).reshape(-1)
            if len(agreement) != n:
                raise ValueError(f"agreement has {len(agreement)} entries, expected {n}")
            put("agreement", agreement)
        for name, width in (("clouds", 3), ("candidates", 4)):
            items = getattr(self, name)
            if items is None:
                continue
            items = list(items)
            if len(items) != n:
                raise ValueError(f"{name} has {len(items)} entries, expected {n}")
            for k, a in enumerate(items):
                if a is not None and (np.ndim(a) != 2 or np.shape(a)[1] != width):
                    raise ValueError(f"{name}[{k}] has shape {np.shape(a)}, expected (K, {width})")
            put(name, items)
        if self.frames is not None:
            frames = list(self.frames)
            if len(frames) != n:
                raise ValueError(f"frames has {len(frames)} entries, expected {n}")
            for k, f in enumerate(frames):
                if f is not None and (len(f) != 2 or f[1] not in FRAME_FORMATS):
                    raise ValueError(f"frames[{k}] must be None or (bytes, one of {FRAME_FORMATS})")
            put("frames", frames)

    @property
    def steps(self) -> int:
        return len(self.stamps)


def replay_topics(stream: ReplayStream) -> dict[str, str]:
    """topic -> message type of what `write_replay_bag` writes for `stream` (optional topics only when given)."""
    from pipeline.rosbag.messages import COMPRESSED, FLOAT32, GRID, POSE_ARRAY, POSE_COV, SCAN, STRING, TF

    out = {TOPICS["map"]: GRID, TOPICS["tf_static"]: TF, TOPICS["tf"]: TF, TOPICS["scan"]: SCAN,
           TOPICS["pose"]: POSE_COV}
    if stream.clouds is not None and any(c is not None for c in stream.clouds):
        out[TOPICS["particles"]] = POSE_ARRAY
    out[TOPICS["state"]] = STRING
    if stream.agreement is not None and np.isfinite(stream.agreement).any():
        out[TOPICS["agreement"]] = FLOAT32
    if stream.candidates is not None and any(c is not None for c in stream.candidates):
        out[TOPICS["candidates"]] = POSE_ARRAY
    if stream.frames is not None and any(f is not None for f in stream.frames):
        out[TOPICS["camera"]] = COMPRESSED
    return out


def write_replay_bag(dst: Path, stream: ReplayStream, *, fmt: str | None = None) -> Path:
    """Write `stream` to `dst` (see the module docstring): `fmt` 'bag' (ROS 1) or 'mcap' (a bare .mcap of ROS 2
    messages); by default 'bag' for a `.bag` suffix, else 'mcap'. An existing file at `dst` is replaced only
    once the new one is complete; an existing folder there is refused (IsADirectoryError)."""
    from pipeline.rosbag.bagfile import BagWriter

    dst = Path(dst)
    fmt = fmt or ("bag" if dst.suffix == ".bag" else "mcap")
    if fmt not in ("bag", "mcap"):
        raise ValueError(f"fmt must be 'bag' or 'mcap', got {fmt!r}")
    if dst.is_dir():
        raise IsADirectoryError(f"{dst} is a folder; the replay is written as one file")
    dst.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    try:
        inner = work / ("out.bag" if fmt == "bag" else "out")
        with BagWriter(inner, fmt, ordered=True) as w:
            for topic, typename in replay_topics(stream).items():
                w.topic(topic, typename, latched=topic in (TOPICS["map"], TOPICS["tf_static"]))
            _write_messages(w, stream)
        made = inner if fmt == "bag" else next(inner.glob("*.mcap"))  # a bare .mcap file, as Foxglove opens
        os.replace(made, dst)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return dst


def _write_messages(w, s: ReplayStream) -> None:
    from pipeline.rosbag.messages import yaw_quat
    from pipeline.runtime.motion import compose2d, inverse2d

    m = w.msgs
    n = s.steps
    if n == 0:
        return
    topics = set(w.conns)
    map_from_odom = compose2d(s.pose, inverse2d(s.odom))
    scan_time = float(np.median(np.diff(s.stamps))) if n > 1 else 0.0

    def tf(stamp, parent, child, xyt):
        return m.transform_stamped(stamp, parent, child, (xyt[0], xyt[1], 0.0), yaw_quat(xyt[2]))

    t0 = float(s.stamps[0])
    occ = s.map
    w.write(TOPICS["map"], t0, m.occupancy_grid(t0, occ.grid, occ.resolution,
                                                (occ.origin_x, occ.origin_y, occ.origin_yaw), s.map_frame))
    w.write(TOPICS["tf_static"], t0, m.tf([tf(t0, s.base_frame, s.laser_frame, s.base_from_laser)]))
    last_state = None
    for k in range(n):
        t = float(s.stamps[k])
        w.write(TOPICS["tf"], t, m.tf([tf(t, s.map_frame, s.odom_frame, map_from_odom[k]),
                                        tf(t, s.odom_frame, s.base_frame, s.odom[k])]))
        w.write(TOPICS["scan"], t, m.laser_scan(t, s.laser_frame, s.ranges[k], s.angle_min, s.angle_increment,
                                                 s.range_min, s.range_max, scan_time, seq=k))
        w.write(TOPICS["pose"], t, m.pose_with_covariance(t, s.pose[k], s.cov[k], s.map_frame, seq=k))
        if s.clouds is not None and s.clouds[k] is not None:
            w.write(TOPICS["particles"], t, m.pose_array(t, s.clouds[k], s.map_frame, seq=k))
        if s.state[k] != last_state:
            w.write(TOPICS["state"], t, m.string(s.state[k]))
            last_state = s.state[k]
        if TOPICS["agreement"] in topics and np.isfinite(s.agreement[k]):
            w.write(TOPICS["agreement"], t, m.float32(s.agreement[k]))
        if s.candidates is not None and s.candidates[k] is not None:
            w.write(TOPICS["candidates"], t, m.pose_array(t, np.asarray(s.candidates[k])[:, :3], s.map_frame,
                                                          seq=k))
        if s.frames is not None and s.frames[k] is not None:
            data, kind = s.frames[k]
            w.write(TOPICS["camera"], t, m.compressed_image(t, s.camera_frame, bytes(data), kind, seq=k))
