"""localize --bag replays a recording exactly as localize replays the ingested site; --write-bag writes it back."""

from __future__ import annotations

import numpy as np

from pipeline.config import load_config
from pipeline.io import tables
from pipeline.localize import run_localize
from pipeline.rosbag.bagfile import open_reader
from pipeline.rosbag.export import run_export_bag
from pipeline.rosbag.messages import stamp_of
from pipeline.rosbag.replay import run_localize_bag
from tests.fixtures.capture_site import write_capture_site


def _estimates(out):
    e = tables.read_table(out / "estimates.parquet", "estimates").to_pydict()
    return np.column_stack([e["x"], e["y"], e["theta"]]), e


def test_bag_replay_equals_the_ingested_run_and_writes_poses(tmp_path):
    from pipeline.ingest import run_ingest

    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site")
    ing = run_ingest(cfg, inputs={"site": site}, outputs={"out": tmp_path / "ing"}, progress=False)
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, progress=False)
    direct = run_localize(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "a"}, init="pose", trials=2,
                          progress=False)
    poses = tmp_path / "poses.mcap"
    via = run_localize_bag(cfg, inputs={"bag": bags / "query_a"}, outputs={"out": tmp_path / "b"}, init="pose",
                           trials=2, write_bag=poses, progress=False)
    pa, ea = _estimates(direct)
    pb, eb = _estimates(via)
    assert np.allclose(pa, pb, atol=1e-9) and ea["state"] == eb["state"] and ea["trial"] == eb["trial"]
    assert np.allclose(np.array(ea["gt_x"], float), np.array(eb["gt_x"], float))

    with open_reader(poses) as reader:
        got = [(c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    pose_msgs = [m for t, m in got if t == "/siteloc/pose"]
    tf_msgs = [tr for t, m in got if t == "/tf" for tr in m.transforms if tr.child_frame_id == "odom"]
    trial0 = pb[np.array(eb["trial"]) == 0]
    assert len(pose_msgs) == len(tf_msgs) == len(trial0) == 9
    xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in pose_msgs])
    assert np.allclose(xy, trial0[:, :2], atol=1e-9)
    stamps = np.array([stamp_of(m) for m in pose_msgs])
    assert np.allclose(np.diff(stamps), 0.5, atol=1e-6)  # the scans' own stamps (2 Hz)
    odom = tables.read_table(ing / "runs" / "query_a.parquet", "runs").to_pydict()
    for k, tr in enumerate(tf_msgs):  # map -> odom composed with the odometry gives the estimate back
        q, t = tr.transform.rotation, tr.transform.translation
        yaw = 2 * np.arctan2(q.z, q.w)
        ox, oy = odom["odom_x"][k], odom["odom_y"][k]
        x = t.x + np.cos(yaw) * ox - np.sin(yaw) * oy
        y = t.y + np.sin(yaw) * ox + np.cos(yaw) * oy
        assert np.allclose([x, y], trial0[k, :2], atol=1e-9)
    assert tr.header.frame_id == "map" and tr.child_frame_id == "odom"


def test_bag_replay_with_a_bundle_equals_the_direct_replay(micro_bundle, tmp_path):
    """The thin runtime (retrieval seeding from the frames) gives the same estimates from the recording."""
    cfg, ing, _, _, bundle = micro_bundle
    site = ing.parent / "site"
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, progress=False)
    query = sorted(p.stem for p in (ing / "runs").glob("query_*.parquet"))[0]
    direct = run_localize(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "a"}, runs=[query],
                          init="retrieval", bundle=bundle, progress=False)
    via = run_localize_bag(cfg, inputs={"bag": bags / query, "bundle": bundle}, outputs={"out": tmp_path / "b"},
                           init="retrieval", progress=False)
    pa, ea = _estimates(direct)
    pb, eb = _estimates(via)
    assert np.allclose(pa, pb, atol=1e-6) and ea["state"] == eb["state"]
