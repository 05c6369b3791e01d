"""Reading one recording into what a capture directory needs: frames, intrinsics, scans, tf, map.

Topics are found by message type (sensor_msgs Image / CompressedImage, CameraInfo, LaserScan,
nav_msgs Odometry and OccupancyGrid; /tf and /tf_static by name); `roles` overrides the choice
(`camera=/front/image_raw`). Stamps are the messages' header stamps (measurement time), shifted by
`offsets[role]` seconds for a sensor whose clock is known to be off. Every problem raises one InputError
naming the topic and the message index; what is dropped (duplicate stamps) is listed in `dropped`.
Frames are checked on the first pass but their bytes are read only for the frames kept (`load_frames`).
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.io.scan_rows import ScanRows, ScanSpool
from pipeline.io.site import Camera, Distortion
from pipeline.rosbag.bagfile import bag_name, messages, open_reader
from pipeline.rosbag.messages import CAMERA_INFO, COMPRESSED, GRID, IMAGE, ODOMETRY, SCAN, TF, stamp_of
from pipeline.rosbag.messages import field as msg_field
from pipeline.rosbag.scans import Grid, cleaned, counter_clockwise, resample
from pipeline.rosbag.transforms import Edge, TfBuffer

ENCODINGS = ("rgb8", "bgr8", "mono8", "jpeg", "png")
ROLE_TYPES = {"camera": (COMPRESSED, IMAGE), "camera_info": (CAMERA_INFO,), "scan": (SCAN,), "odom": (ODOMETRY,),
              "map": (GRID,)}
ROLES = tuple(ROLE_TYPES)
#: tf's message types: tf2_msgs/TFMessage, and tf/tfMessage of ROS 1 recordings made before tf2 (same fields).
TF_TYPES = (TF, "tf/msg/tfMessage")


@dataclass
class Recording:
    path: Path
    name: str
    # stamp, message index, bytes (None until `load_frames`), jpeg|png
    frames: list[tuple[float, int, bytes | None, str]] = field(default_factory=list)
    camera_frame: str | None = None
    intrinsics: Camera | None = None
    scan_stamps: np.ndarray | None = None
    ranges: ScanRows | None = None  # (N, beams) float32, read from a spool file a block at a time
    laser: dict | None = None  # angle_min, angle_increment, beams, range_min, range_max (radians, m), CCW
    resampled_scans: int = 0  # scans whose beam count or sweep differed from the first's (scans.resample)
    laser_frame: str | None = None
    odom_frame: str | None = None
    base_frame: str | None = None
    tf: TfBuffer = field(default_factory=TfBuffer)
    grid: object | None = None  # OccupancyMap
    topics: dict[str, str] = field(default_factory=dict)  # role -> topic
    dropped: list[dict] = field(default_factory=list)
    messages: int = 0  # messages read
    odom_msgs: Edge = field(default_factory=lambda: Edge("odom", "base", False))  # the odometry topic's poses
    odometry_source: str | None = None  # "tf" (odom -> base in /tf) or "topic" (the odometry topic)


def _fail(path: Path, topic: str | None, message: str, fix: str, index: int | None = None):
    where = f"{path}" + (f" {topic}" if topic else "") + (f" message {index}" if index is not None else "")
    raise InputError(f"{path}: cannot use the recording", [Problem(where, message, fix=fix)])


def choose_topics(path: Path, connections, roles: dict[str, str]) -> dict[str, str]:
    """role -> topic: the overrides, else the one topic of the role's types (several: an error)."""
    by_topic = {c.topic: c.msgtype for c in connections}
    out: dict[str, str] = {}
    for role, types in ROLE_TYPES.items():
        if role in roles:
            topic = roles[role]
            if topic not in by_topic:
                _fail(path, topic, f"--topic {role}={topic}: no such topic (it has {sorted(by_topic)})",
                      "name a topic of the recording (see `siteloc ingest-bag --list`)")
            if by_topic[topic] not in types:
                _fail(path, topic, f"is {by_topic[topic]}, a {role} topic must be one of {list(types)}",
                      f"pick a {role} topic of the right type")
            out[role] = topic
            continue
        found = sorted(t for t, ty in by_topic.items() if ty in types)
        if role == "camera" and len(found) > 1:  # image_raw and image_raw/compressed of one camera: prefer raw
            compressed = [t for t in found if by_topic[t] == COMPRESSED]
            found = compressed if len(compressed) == 1 else found
        if len(found) > 1:
            _fail(path, None, f"several {role} topics: {found}", f"choose one with --topic {role}=NAME")
        if found:
            out[role] = found[0]
    for name in ("/tf", "/tf_static"):
        if name in by_topic and by_topic[name] not in TF_TYPES:
            _fail(path, name, f"is {by_topic[name]}, not a tf message ({' or '.join(TF_TYPES)})",
                  f"record tf as tf2_msgs/TFMessage on {name}")
        if name in by_topic:
            out[name.strip("/")] = name
    return out


def _image_bytes(path: Path, topic: str, index: int, msg, typename: str,
                 encode: bool = True) -> tuple[bytes | None, str, tuple[int, int]]:
    """(file bytes or None without `encode`, jpeg|png, (width, height)) of an image message, checked: the
    header of every message, and with `encode` (the frames kept) the whole image, which finds truncation."""
    from PIL import Image

    from pipeline.io.images import ImageError, image_size, open_image

    if typename == COMPRESSED:
        data = bytes(msg.data)
        fmt = "jpeg" if data[:3] == b"\xff\xd8\xff" else "png" if data[:8] == b"\x89PNG\r\n\x1a\n" else None
        if fmt is None:
            _fail(path, topic, f"compressed image data is neither JPEG nor PNG (format '{msg.format}', first bytes "
                  f"{data[:8].hex()})", f"siteloc reads {', '.join(ENCODINGS)} (re-encode, e.g. with image_transport "
                  "republish)", index)
        try:
            size = open_image(data, rgb=False).size if encode else image_size(data)
        except ImageError as exc:
            _fail(path, topic, f"{fmt.upper()} image data cannot be decoded: {exc.message}",
                  "re-record it, or republish the images as 8-bit JPEG or PNG", index)
        return (data if encode else None), fmt, size
    enc = msg.encoding.lower()
    if enc not in ("rgb8", "bgr8", "mono8"):
        _fail(path, topic, f"image encoding '{msg.encoding}' is not supported",
              f"siteloc reads {', '.join(ENCODINGS)}", index)
    ch = 1 if enc == "mono8" else 3
    raw = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < msg.width * ch or raw.size < msg.step * msg.height:
        _fail(path, topic, f"image data has {raw.size} bytes, {msg.height} rows of step {msg.step} need more",
              "the message is damaged; re-record it", index)
    size = (int(msg.width), int(msg.height))
    if not encode:
        return None, "png", size
    px = raw[: msg.step * msg.height].reshape(msg.height, msg.step)[:, : msg.width * ch]
    px = px.reshape(msg.height, msg.width, ch) if ch == 3 else px
    if enc == "bgr8":
        px = px[:, :, ::-1]
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(px)).save(buf, format="PNG")
    return buf.getvalue(), "png", size


def _intrinsics(path: Path, topic: str, index: int, msg) -> Camera:
    k = np.asarray(msg_field(msg, "k"), dtype=np.float64)
    d = np.asarray(msg_field(msg, "d"), dtype=np.float64)
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        _fail(path, topic, f"camera matrix K {k.tolist()} has no focal length",
              "the camera is not calibrated: calibrate it (camera_calibration) and record CameraInfo", index)
    distortion = None
    if d.size and np.any(np.abs(d) > 1e-9):
        model = str(msg_field(msg, "distortion_model"))
        plumb_bob = (model == "plumb_bob" and d.size == 5) or (
            model == "rational_polynomial" and d.size == 8 and not np.any(np.abs(d[5:]) > 1e-9))
        if not plumb_bob:
            _fail(path, topic, f"distortion model '{model}' with D={np.round(d, 4).tolist()}: siteloc reads "
                  "plumb_bob (5 coefficients, or rational_polynomial with k4 = k5 = k6 = 0) or rectified images",
                  "record the rectified topic (image_rect, from image_proc) and its CameraInfo", index)
        distortion = Distortion(coeffs=tuple(float(c) for c in d[:5]))
    if msg.width <= 0 or msg.height <= 0:
        _fail(path, topic, f"CameraInfo says the image is {msg.width}x{msg.height}",
              "record the CameraInfo the camera driver publishes with its calibration", index)
    return Camera(width=int(msg.width), height=int(msg.height), fx=float(k[0]), fy=float(k[4]), cx=float(k[2]),
                  cy=float(k[5]), distortion=distortion)


def _scan(rec: Recording, path: Path, topic: str, index: int, msg, scans: ScanSpool) -> None:
    """One LaserScan onto the recording's beam grid (the first scan's; `pipeline.rosbag.scans`)."""
    n, inc = len(msg.ranges), float(msg.angle_increment)
    if n < 2 or inc == 0 or not math.isfinite(inc) or not math.isfinite(float(msg.angle_min)):
        _fail(path, topic, f"{n} beams with angle_min {msg.angle_min}, angle_increment {msg.angle_increment}",
              "siteloc needs scans of at least 2 beams with a finite, non-zero angle_increment", index)
    if not float(msg.range_max) > 0 or not math.isfinite(float(msg.range_max)):
        _fail(path, topic, f"range_max is {msg.range_max}", "the laser driver must publish its finite range_max",
              index)
    ranges, grid = counter_clockwise(np.asarray(msg.ranges, dtype=np.float32), float(msg.angle_min), inc)
    ranges = cleaned(ranges, float(msg.range_min), float(msg.range_max))
    if rec.laser is None:
        rec.laser, rec.laser_frame = {"angle_min": grid.angle_min, "angle_increment": grid.angle_increment,
                                      "beams": grid.beams, "range_min": max(float(msg.range_min), 0.0),
                                      "range_max": float(msg.range_max)}, msg.header.frame_id.lstrip("/")
    first = Grid(rec.laser["angle_min"], rec.laser["angle_increment"], rec.laser["beams"])
    if grid != first:
        if not first.fits(grid):
            _fail(path, topic, f"scan geometry changes: {grid.beams} beams from {math.degrees(grid.angle_min):.2f} "
                  f"to {math.degrees(grid.angle_max):.2f} deg, the first scan has {first.beams} from "
                  f"{math.degrees(first.angle_min):.2f} to {math.degrees(first.angle_max):.2f} deg",
                  "one laser configuration per recording: split the recording where the driver was reconfigured",
                  index)
        ranges = resample(ranges, grid, first)
        rec.resampled_scans += 1
    scans.append(ranges)


def read_recording(path: Path, roles: dict[str, str] | None = None, offsets: dict[str, float] | None = None,
                   tf_max_gap: float = 0.5, tolerance: float = 0.05, progress: bool = False) -> Recording:
    """Read a bag (see module docstring); raises InputError on anything siteloc cannot use."""
    from pipeline.io.map_yaml import OccupancyMap
    from pipeline.progress import progress_bar

    path, roles, offsets = Path(path), roles or {}, offsets or {}
    rec = Recording(path, bag_name(path), tf=TfBuffer(tf_max_gap, tolerance))
    with open_reader(path) as reader:
        rec.topics = topics = choose_topics(path, reader.connections, roles)
        if "camera" not in topics and "scan" not in topics:
            _fail(path, None, "has no camera (sensor_msgs/Image or CompressedImage) and no LaserScan topic",
                  "record the camera and the laser; `siteloc ingest-bag --list` shows what the bag holds")
        if "camera" in topics and "camera_info" not in topics:
            _fail(path, topics["camera"], "has images but no sensor_msgs/CameraInfo topic",
                  "record the camera's camera_info topic (it gives the intrinsics)")
        wanted = {t: r for r, t in topics.items()}
        conns = [c for c in reader.connections if c.topic in wanted]
        counts = {t: 0 for t in wanted}
        last_stamp: dict[str, float] = {}
        scan_stamps, sizes = [], []
        scans = ScanSpool()  # on disk, read back a block at a time: a long drive's scans are never all held
        first_info: tuple[int, Camera] | None = None
        total = sum(c.msgcount for c in conns)
        msgs = messages(reader, path, conns)
        for conn, _, raw in progress_bar(msgs, total=total, desc=f"reading {rec.name}", unit="msg",
                                         enabled=progress, leave=False):
            topic, role = conn.topic, wanted[conn.topic]
            index = counts[topic]
            counts[topic] += 1
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                _fail(path, topic, f"cannot be decoded: {exc}", "the recording is damaged; re-record it", index)
            if role in ("tf", "tf_static"):
                for tr in msg.transforms:
                    t, q = tr.transform.translation, tr.transform.rotation
                    err = rec.tf.add(tr.header.frame_id, tr.child_frame_id, stamp_of(tr),
                                     (t.x, t.y, t.z), (q.x, q.y, q.z, q.w), static=role == "tf_static")
                    if err:
                        _fail(path, topic, err, "the tf tree must be a tree: one parent per frame", index)
                continue
            if role == "map":
                if rec.grid is None:
                    info = msg.info
                    q = info.origin.orientation
                    yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
                    grid = np.asarray(msg.data, dtype=np.int8).reshape(info.height, info.width)
                    grid = np.where((grid > 0) & (grid < 100), np.int8(-1), grid).astype(np.int8)  # trinary
                    # resolution is float32 in the message: 0.05 arrives as 0.0500000007; micrometres are plenty
                    rec.grid = OccupancyMap(grid, round(float(info.resolution), 6), float(info.origin.position.x),
                                            float(info.origin.position.y), yaw)
                continue
            stamp = stamp_of(msg) + offsets.get(role, 0.0)
            prev = last_stamp.get(topic)
            if prev is not None and stamp < prev - 1e-6:
                _fail(path, topic, f"stamps out of order: {stamp:.6f} s after {prev:.6f} s",
                      "sensor clocks jumped back; re-record, or cut the recording at the jump (ros2 bag convert "
                      "with a time range)", index)
            if prev is not None and abs(stamp - prev) <= 1e-6:
                rec.dropped.append({"topic": topic, "index": index, "stamp": stamp, "reason": "duplicate stamp"})
                continue
            last_stamp[topic] = stamp
            if role == "odom":
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                rec.odom_frame = rec.odom_frame or msg.header.frame_id.lstrip("/")
                rec.base_frame = rec.base_frame or msg.child_frame_id.lstrip("/")
                rec.odom_msgs.add(stamp, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
            elif role == "camera_info":
                k = _intrinsics(path, topic, index, msg)
                if first_info is None:
                    first_info = (index, k)
                    rec.intrinsics = k
                elif k != first_info[1]:
                    _fail(path, topic, f"intrinsics change: {k} after {first_info[1]} (message {first_info[0]})",
                          "one calibration per recording: split the bag where the camera was recalibrated", index)
            elif role == "camera":
                _, fmt, size = _image_bytes(path, topic, index, msg, conn.msgtype, encode=False)
                rec.camera_frame = rec.camera_frame or msg.header.frame_id.lstrip("/")
                rec.frames.append((stamp, index, None, fmt))
                sizes.append((index, size))
            elif role == "scan":
                _scan(rec, path, topic, index, msg, scans)
                scan_stamps.append(stamp)
    rec.messages = sum(counts.values())
    if len(scans):
        rec.ranges, rec.scan_stamps = scans.rows(), np.asarray(scan_stamps)
    if rec.odom_msgs and rec.tf.path(rec.odom_frame, rec.base_frame) is None:  # only on /odom: it is the edge
        for stamp, xyz, quat in zip(*rec.odom_msgs.arrays(), strict=True):
            rec.tf.add(rec.odom_frame, rec.base_frame, float(stamp), xyz, quat, static=False)
        rec.odometry_source = "topic"
    elif rec.tf.edges:
        rec.odometry_source = "tf"
    if rec.frames and rec.intrinsics is not None:
        k = rec.intrinsics
        for index, size in sizes:
            if size != (k.width, k.height):
                _fail(path, topics["camera"], f"image is {size[0]}x{size[1]}, CameraInfo says {k.width}x{k.height}",
                      "record the CameraInfo that belongs to this image topic", index)
    return rec


def load_frames(rec: Recording, wanted) -> None:
    """Fill in the bytes of the frames at positions `wanted` of `rec.frames` (a second pass over the camera
    topic): only the frames a capture directory keeps are ever held in memory, however long the drive."""
    want = {rec.frames[i][1]: i for i in wanted if rec.frames[i][2] is None}
    if not want:
        return
    topic = rec.topics["camera"]
    with open_reader(rec.path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for index, (conn, _, raw) in enumerate(messages(reader, rec.path, conns)):
            i = want.get(index)
            if i is None:
                continue
            data, _, _ = _image_bytes(rec.path, topic, index, reader.deserialize(raw, conn.msgtype), conn.msgtype)
            stamp, _, _, fmt = rec.frames[i]
            rec.frames[i] = (stamp, index, data, fmt)
