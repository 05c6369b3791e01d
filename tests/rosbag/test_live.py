"""localize --bag --live: a Foxglove WebSocket client on 127.0.0.1 receives the replay as it runs.

The client speaks the Foxglove WebSocket protocol itself (the `websockets` package): it reads the server's
channel advertisements, subscribes, and decodes the protobuf messages with the schemas the server sends,
so what it checks is what Foxglove would show, against the estimates the replay wrote.
"""

from __future__ import annotations

import base64
import json
import struct
import threading
import time

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

from pipeline.config import load_config  # noqa: E402
from pipeline.io import tables  # noqa: E402
from tests.fixtures.robot_recordings import Traits, floor_map, record, write_map_yaml  # noqa: E402


def _decoder(channel: dict):
    """A function bytes -> protobuf message for an advertised protobuf channel (its FileDescriptorSet)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString


def test_a_client_on_localhost_sees_the_replay_as_it_runs(tmp_path):
    from websockets.sync.client import connect

    from pipeline.rosbag.replay import run_localize_bag

    occ = floor_map(0.05)
    rec = record(tmp_path / "rec", occ, Traits(seconds=6.0, reference=False, laser_yaw_deg=90.0))
    map_yaml = write_map_yaml(tmp_path / "map.yaml", occ)
    urls, errors = [], []

    def replay():
        try:
            run_localize_bag(load_config("demo"), inputs={"bag": rec.path, "map": map_yaml},
                             outputs={"out": tmp_path / "o"}, init="pose", start_pose=tuple(rec.gt[0]),
                             progress=False, live={"port": 0, "speed": 0.0, "wait_s": 30.0, "on_start": urls.append})
        except Exception as exc:  # noqa: BLE001 - reported by the test below
            errors.append(exc)

    worker = threading.Thread(target=replay)
    worker.start()
    deadline = time.monotonic() + 30
    while not urls and worker.is_alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert urls and urls[0].startswith("ws://127.0.0.1:"), errors
    got: dict[str, list] = {}
    with connect(urls[0], subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
        assert json.loads(ws.recv())["op"] == "serverInfo"
        adv = json.loads(ws.recv())
        assert adv["op"] == "advertise"
        channels = {c["id"]: c for c in adv["channels"]}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid} for cid in channels]}))
        decode = {cid: (json.loads if c["encoding"] == "json" else _decoder(c)) for cid, c in channels.items()}
        try:
            while True:
                frame = ws.recv(timeout=20)
                if isinstance(frame, bytes) and frame[0] == 1:  # messageData: op, subscription, log time, payload
                    sub, log_ns = struct.unpack_from("<IQ", frame, 1)
                    got.setdefault(channels[sub]["topic"], []).append((log_ns, decode[sub](frame[13:])))
        except Exception:  # noqa: BLE001 - the server stops when the replay ends: the connection closes
            pass
    worker.join(60)
    assert not errors, errors
    e = tables.read_table(tmp_path / "o" / "estimates.parquet", "estimates").to_pydict()
    steps = len(e["x"])
    assert {"/map", "/tf", "/siteloc/scan", "/siteloc/pose", "/siteloc/particles", "/siteloc/status"} <= set(got)
    poses = got["/siteloc/pose"]
    assert len(poses) == steps  # every step, in order, stamped with the scans' stamps
    assert np.allclose([p.pose.position.x for _, p in poses], e["x"], atol=1e-9)
    assert np.allclose([p.pose.position.y for _, p in poses], e["y"], atol=1e-9)
    assert np.allclose([t * 1e-9 for t, _ in poses], rec.stamps, atol=1e-6)
    status = [m for _, m in got["/siteloc/status"]]
    assert [s["state"] for s in status] == e["state"]
    assert np.allclose([s["agreement"] for s in status], e["agreement"], atol=1e-6)
    grid = got["/map"][0][1]
    assert grid.column_count == occ.grid.shape[1] and len(grid.data) == occ.grid.size
    cells = np.frombuffer(grid.data, np.uint8).reshape(occ.grid.shape)
    assert np.array_equal(cells == 100, occ.grid == 100) and np.array_equal(cells == 255, occ.grid < 0)
    updated = int(np.sum(e["updated"])) + (0 if e["updated"][0] else 1)
    assert len(got["/siteloc/particles"]) == updated  # the particles where the filter updated
    # map -> odom -> base in /tf composes to the estimate
    tf = got["/tf"][-1][1].transforms
    by_child = {t.child_frame_id: t for t in tf}
    assert set(by_child) == {"odom", "base_link", "laser_2d"}

    def se2(t):
        return np.array([t.translation.x, t.translation.y, 2 * np.arctan2(t.rotation.z, t.rotation.w)])

    a, b = se2(by_child["odom"]), se2(by_child["base_link"])
    c, s = np.cos(a[2]), np.sin(a[2])
    assert np.allclose([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1]], [e["x"][-1], e["y"][-1]], atol=1e-6)


def test_live_refuses_a_port_in_use_clearly(tmp_path):
    import socket

    from pipeline.errors import ConfigError
    from pipeline.rosbag.replay import run_localize_bag

    occ = floor_map(0.05)
    rec = record(tmp_path / "rec", occ, Traits(seconds=3.0, reference=False))
    map_yaml = write_map_yaml(tmp_path / "map.yaml", occ)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f"cannot serve on 127.0.0.1:{port}"):
            run_localize_bag(load_config("demo"), inputs={"bag": rec.path, "map": map_yaml},
                             outputs={"out": tmp_path / "o"}, progress=False, live={"port": port, "speed": 0.0})
    assert not (tmp_path / "o").exists()
