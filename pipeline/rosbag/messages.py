"""ROS message types for both ROS generations, built and serialised with `rosbags`' typestores.

ROS 1 and ROS 2 spell a few fields differently (CameraInfo's `K` / `k`, Header's `seq`); `Messages`
hides that so the writer and the reader name fields once. Stamps are float seconds inside siteloc and
`builtin_interfaces/Time` (sec, nanosec) in the bag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FORMATS = ("mcap", "db3", "bag")

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
GRID = "nav_msgs/msg/OccupancyGrid"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
STRING = "std_msgs/msg/String"
FLOAT32 = "std_msgs/msg/Float32"

ROS1_NAMES = {"d": "D", "k": "K", "r": "R", "p": "P"}  # CameraInfo's fields in ROS 1


def stamp_of(msg) -> float:
    """header.stamp in seconds."""
    s = msg.header.stamp
    return s.sec + s.nanosec * 1e-9


def field(msg, name: str):
    """A field by its ROS 2 name, whichever generation wrote the message."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, ROS1_NAMES.get(name, name))


def ns(stamp: float) -> int:
    """Seconds as integer nanoseconds (bag time), rounded to the microsecond the writer keeps."""
    return int(round(stamp * 1e6)) * 1000


@dataclass
class Messages:
    """Builders of the messages siteloc writes, for one generation ('ros1' or 'ros2')."""

    generation: str

    def __post_init__(self):
        self.store = typestore(self.generation)
        self.T = self.store.types

    @classmethod
    def for_format(cls, fmt: str) -> Messages:
        return cls("ros1" if fmt == "bag" else "ros2")

    def serialize(self, msg) -> bytes:
        if self.generation == "ros1":
            return bytes(self.store.serialize_ros1(msg, msg.__msgtype__))
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def time(self, stamp: float):
        n = ns(stamp)
        return self.T["builtin_interfaces/msg/Time"](sec=n // 1_000_000_000, nanosec=n % 1_000_000_000)

    def header(self, stamp: float, frame_id: str, seq: int = 0):
        H = self.T["std_msgs/msg/Header"]
        if self.generation == "ros1":
            return H(seq=seq, stamp=self.time(stamp), frame_id=frame_id)
        return H(stamp=self.time(stamp), frame_id=frame_id)

    def _make(self, typename: str, **fields):
        if self.generation == "ros1":
            fields = {ROS1_NAMES.get(k, k) if typename == CAMERA_INFO else k: v for k, v in fields.items()}
        return self.T[typename](**fields)

    def pose(self, xyz, quat):
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(quat[0]), y=float(quat[1]), z=float(quat[2]),
                                                          w=float(quat[3])))

    def transform_stamped(self, stamp: float, parent: str, child: str, xyz, quat):
        T = self.T
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=float(quat[0]), y=float(quat[1]), z=float(quat[2]),
                                                       w=float(quat[3])))
        return T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp, parent), child_frame_id=child,
                                                       transform=tr)

    def tf(self, transforms: list):
        return self.T[TF](transforms=transforms)

    def compressed_image(self, stamp: float, frame_id: str, data: bytes, fmt: str, seq: int = 0):
        return self._make(COMPRESSED, header=self.header(stamp, frame_id, seq), format=fmt,
                          data=np.frombuffer(data, dtype=np.uint8))

    def raw_image(self, stamp: float, frame_id: str, pixels: np.ndarray, encoding: str, seq: int = 0):
        h, w = pixels.shape[:2]
        channels = 1 if pixels.ndim == 2 else pixels.shape[2]
        return self._make(IMAGE, header=self.header(stamp, frame_id, seq), height=h, width=w, encoding=encoding,
                          is_bigendian=0, step=w * channels, data=np.ascontiguousarray(pixels).ravel())

    def camera_info(self, stamp: float, frame_id: str, width: int, height: int, fx: float, fy: float, cx: float,
                    cy: float, seq: int = 0, d=None):
        """A plumb_bob CameraInfo; `d` its (k1, k2, p1, p2, k3), zero (rectified) when not given."""
        k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
        p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        d = np.zeros(5) if d is None else np.asarray(d, dtype=np.float64)
        return self._make(CAMERA_INFO, header=self.header(stamp, frame_id, seq), height=height, width=width,
                          distortion_model="plumb_bob", d=d, k=k, r=np.eye(3).ravel(), p=p,
                          binning_x=0, binning_y=0, roi=roi)

    def scan(self, stamp: float, frame_id: str, ranges: np.ndarray, angle_min: float, angle_increment: float,
             range_max: float, scan_time: float, seq: int = 0):
        n = len(ranges)
        return self._make(SCAN, header=self.header(stamp, frame_id, seq), angle_min=float(angle_min),
                          angle_max=float(angle_min + (n - 1) * angle_increment),
                          angle_increment=float(angle_increment), time_increment=0.0, scan_time=float(scan_time),
                          range_min=0.0, range_max=float(range_max), ranges=np.asarray(ranges, dtype=np.float32),
                          intensities=np.zeros(0, dtype=np.float32))

    def odometry(self, stamp: float, pose_xyt, frame_id: str = "odom", child: str = "base_link", seq: int = 0):
        T = self.T
        x, y, th = (float(v) for v in pose_xyt)
        cov = np.zeros(36)
        cov[[0, 7, 35]] = (1e-4, 1e-4, 1e-4)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose((x, y, 0.0), yaw_quat(th)), covariance=cov)
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        twist = T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero,
                                                                                              angular=zero),
                                                          covariance=np.zeros(36))
        return self._make(ODOMETRY, header=self.header(stamp, frame_id, seq), child_frame_id=child, pose=pose,
                          twist=twist)

    def occupancy_grid(self, stamp: float, grid: np.ndarray, resolution: float, origin_xyt, frame_id: str = "map"):
        T = self.T
        h, w = grid.shape
        info = T["nav_msgs/msg/MapMetaData"](
            map_load_time=self.time(stamp), resolution=float(resolution), width=w, height=h,
            origin=self.pose((origin_xyt[0], origin_xyt[1], 0.0), yaw_quat(origin_xyt[2])))
        return self._make(GRID, header=self.header(stamp, frame_id), info=info,
                          data=np.ascontiguousarray(grid, dtype=np.int8).ravel())

    def pose_with_covariance(self, stamp: float, pose_xyt, cov3: np.ndarray, frame_id: str = "map", seq: int = 0):
        T = self.T
        cov = np.zeros((6, 6))
        idx = [0, 1, 5]
        cov[np.ix_(idx, idx)] = np.asarray(cov3, dtype=np.float64)
        pwc = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=self.pose((pose_xyt[0], pose_xyt[1], 0.0), yaw_quat(pose_xyt[2])), covariance=cov.ravel())
        return self._make(POSE_COV, header=self.header(stamp, frame_id, seq), pose=pwc)

    def laser_scan(self, stamp: float, frame_id: str, ranges: np.ndarray, angle_min: float, angle_increment: float,
                   range_min: float, range_max: float, scan_time: float = 0.0, seq: int = 0):
        """A LaserScan with its range_min (`scan` writes 0)."""
        msg = self.scan(stamp, frame_id, ranges, angle_min, angle_increment, range_max, scan_time, seq)
        msg.range_min = float(range_min)
        return msg

    def pose_array(self, stamp: float, poses_xyt: np.ndarray, frame_id: str = "map", seq: int = 0):
        """geometry_msgs/PoseArray of (N, 3) x, y, heading on the floor (z = 0)."""
        T = self.T
        Pose, Point, Quat = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
        p = np.asarray(poses_xyt, dtype=np.float64).reshape(-1, 3)
        rows = np.column_stack([p[:, 0], p[:, 1], np.sin(p[:, 2] / 2.0), np.cos(p[:, 2] / 2.0)]).tolist()
        poses = [Pose(position=Point(x=x, y=y, z=0.0), orientation=Quat(x=0.0, y=0.0, z=qz, w=qw))
                 for x, y, qz, qw in rows]
        return T[POSE_ARRAY](header=self.header(stamp, frame_id, seq), poses=poses)

    def string(self, text: str):
        return self.T[STRING](data=str(text))

    def float32(self, value: float):
        return self.T[FLOAT32](data=float(value))


def typestore(generation: str):
    """rosbags' typestore of a generation; ROS 1's lacks tf2_msgs/TFMessage (tf's message), so it is added."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if generation != "ros1":
        return get_typestore(Stores.ROS2_HUMBLE)
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    return store


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of a rotation about z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))
