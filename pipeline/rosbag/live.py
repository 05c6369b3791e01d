"""A live view of a replay: a Foxglove WebSocket server on localhost that publishes each step as it runs.

`siteloc localize --bag REC --live` starts it (the optional `foxglove-sdk` package: `pip install
'siteloc[live]'`); Foxglove connects with "Open connection" > Foxglove WebSocket > ws://127.0.0.1:8765.
It publishes what the replay recording holds (`replay_bag`), as Foxglove's own schemas: the map
(`/map`, a Grid, again every few seconds so a late client sees it), the scan in the levelled laser frame,
the transforms map -> odom -> base -> laser, the estimate, the particles, and the filter's status
(state, agreement, spread) as JSON. Steps are paced at the recording's speed times `speed` (0: as fast
as the filter runs); `wait_s` waits for a client to subscribe before the first step.
"""

from __future__ import annotations

import json
import math
import threading
import time

import numpy as np

from pipeline.runtime.motion import compose2d, inverse2d

#: Seconds between two publications of the map (a client that connects later still gets it).
MAP_EVERY_S = 2.0


def _need_sdk():
    try:
        import foxglove
    except ImportError:
        from pipeline.errors import ConfigError

        raise ConfigError("--live needs the foxglove-sdk package: pip install 'siteloc[live]' (or foxglove-sdk)") \
            from None
    return foxglove


class LiveView:
    """Publish a replay step by step (see module docstring). Use as a context manager around the replay."""

    def __init__(self, occ_map, stamps: np.ndarray, odom: np.ndarray, ranges: np.ndarray, angle_min: float,
                 angle_increment: float, base_from_laser: tuple[float, float, float], *, frames: dict[str, str],
                 host: str = "127.0.0.1", port: int = 8765, speed: float = 1.0, wait_s: float = 0.0):
        self.occ, self.stamps, self.odom, self.ranges = occ_map, np.asarray(stamps), np.asarray(odom), ranges
        self.angle_min, self.angle_increment, self.mount = float(angle_min), float(angle_increment), base_from_laser
        self.frames, self.host, self.port, self.speed, self.wait_s = frames, host, int(port), float(speed), wait_s
        self.server = None
        self._t0 = self._last_map = None

    def __enter__(self) -> LiveView:
        fox = _need_sdk()
        from foxglove import channels

        class Subscribed(fox.ServerListener):  # notes the first subscription (`wait_s`)
            def __init__(self):
                self.event = threading.Event()

            def on_subscribe(self, client, channel) -> None:
                self.event.set()

        self._listener = Subscribed()
        try:
            self.server = fox.start_server(name="siteloc", host=self.host, port=self.port,
                                           server_listener=self._listener)
        except Exception as exc:  # the SDK raises its own error for a port in use
            from pipeline.errors import ConfigError

            raise ConfigError(f"--live: cannot serve on {self.host}:{self.port}: {exc} (choose --live-port)") \
                from None
        self.port = self.server.port
        self.ch = {"map": channels.GridChannel("/map"), "scan": channels.LaserScanChannel("/siteloc/scan"),
                   "tf": channels.FrameTransformsChannel("/tf"), "pose": channels.PoseInFrameChannel("/siteloc/pose"),
                   "particles": channels.PosesInFrameChannel("/siteloc/particles"),
                   "status": fox.Channel("/siteloc/status", message_encoding="json", schema={
                       "type": "object", "properties": {k: {"type": t} for k, t in (
                           ("step", "integer"), ("state", "string"), ("agreement", "number"), ("spread_m", "number"),
                           ("x", "number"), ("y", "number"), ("theta_deg", "number"))}})}
        return self

    def wait_for_client(self) -> bool:
        """Wait up to `wait_s` for a client to subscribe; whether one did."""
        if self.wait_s > 0 and self._listener.event.wait(self.wait_s):
            time.sleep(0.2)  # a client subscribes to its channels one after the other
            return True
        return False

    def __exit__(self, *exc) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _stamp(self, t: int):
        from foxglove.messages import Timestamp

        s = float(self.stamps[t])
        return Timestamp(sec=int(s), nsec=int(round((s - int(s)) * 1e9)) % 1_000_000_000)

    def _pace(self, t: int) -> None:
        if self.speed <= 0:
            return
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now - (self.stamps[t] - self.stamps[0]) / self.speed
        wait = self._t0 + (self.stamps[t] - self.stamps[0]) / self.speed - now
        if wait > 0:
            time.sleep(wait)

    def step(self, t: int, pose, state: str, particles=None, agreement: float | None = None,
             spread: float | None = None) -> None:
        """Publish step t (map_from_base `pose`, the particles (K, 3) when they changed)."""
        from foxglove.messages import FrameTransform, FrameTransforms, LaserScan, PoseInFrame, PosesInFrame

        self._pace(t)
        ts, f = self._stamp(t), self.frames
        now = time.monotonic()
        if self._last_map is None or now - self._last_map >= MAP_EVERY_S:
            self.ch["map"].log(self._grid(ts), log_time=self._ns(t))
            self._last_map = now
        odom = self.odom[t]
        map_from_odom = compose2d(np.asarray(pose, float)[None], inverse2d(odom[None]))[0]
        tfs = [FrameTransform(timestamp=ts, parent_frame_id=f["map"], child_frame_id=f["odom"],
                              translation=_vec(map_from_odom), rotation=_quat(map_from_odom[2])),
               FrameTransform(timestamp=ts, parent_frame_id=f["odom"], child_frame_id=f["base"],
                              translation=_vec(odom), rotation=_quat(odom[2])),
               FrameTransform(timestamp=ts, parent_frame_id=f["base"], child_frame_id=f["laser"],
                              translation=_vec(self.mount), rotation=_quat(self.mount[2]))]
        log_time = self._ns(t)
        self.ch["tf"].log(FrameTransforms(transforms=tfs), log_time=log_time)
        r = np.asarray(self.ranges[t], dtype=np.float64)
        self.ch["scan"].log(LaserScan(timestamp=ts, frame_id=f["laser"], pose=_pose((0.0, 0.0, 0.0)),
                                      start_angle=self.angle_min,
                                      end_angle=self.angle_min + (len(r) - 1) * self.angle_increment,
                                      ranges=np.where(np.isfinite(r), r, math.inf).tolist()), log_time=log_time)
        self.ch["pose"].log(PoseInFrame(timestamp=ts, frame_id=f["map"], pose=_pose(pose)), log_time=log_time)
        if particles is not None:
            self.ch["particles"].log(PosesInFrame(timestamp=ts, frame_id=f["map"],
                                                  poses=[_pose(p) for p in np.asarray(particles, float)]),
                                     log_time=log_time)
        status = {"step": int(t), "state": str(state), "x": float(pose[0]), "y": float(pose[1]),
                  "theta_deg": math.degrees(float(pose[2]))}
        for key, v in (("agreement", agreement), ("spread_m", spread)):
            if v is not None and math.isfinite(v):
                status[key] = float(v)
        self.ch["status"].log(json.dumps(status), log_time=log_time)

    def _ns(self, t: int) -> int:
        return int(round(float(self.stamps[t]) * 1e9))

    def _grid(self, ts):
        from foxglove.messages import Grid, PackedElementField, PackedElementFieldNumericType, Vector2

        occ = self.occ
        h, w = occ.grid.shape
        cells = np.where(occ.grid < 0, 255, occ.grid).astype(np.uint8)  # 0 free .. 100 occupied, 255 unknown
        return Grid(timestamp=ts, frame_id=self.frames["map"],
                    pose=_pose((occ.origin_x, occ.origin_y, occ.origin_yaw)), column_count=w,
                    cell_size=Vector2(x=occ.resolution, y=occ.resolution), row_stride=w, cell_stride=1,
                    fields=[PackedElementField(name="occupancy", offset=0, type=PackedElementFieldNumericType.Uint8)],
                    data=cells.tobytes())


def _vec(p):
    from foxglove.messages import Vector3

    return Vector3(x=float(p[0]), y=float(p[1]), z=0.0)


def _quat(yaw: float):
    from foxglove.messages import Quaternion

    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _pose(p):
    from foxglove.messages import Pose

    return Pose(position=_vec(p), orientation=_quat(float(p[2])))
