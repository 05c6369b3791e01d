"""The localization replay written as one recording (write_replay_bag) and the run overview figure."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.io.map_yaml import OccupancyMap
from pipeline.rosbag.bagfile import BagWriter, open_reader
from pipeline.rosbag.messages import stamp_of
from pipeline.rosbag.replay_bag import TOPICS, ReplayStream, write_replay_bag

T = 20
BEAMS = 16
STATES = ["relocalising"] * 5 + ["tracking"] * 8 + ["lost"] * 3 + ["tracking"] * 4  # changes at 0, 5, 13, 16
CLOUD_STEPS = [k for k in range(T) if k % 3 != 1]  # the others have None
CANDIDATE_STEPS = [0, 1, 2, 13, 14]
FRAME_STEPS = [0, 4, 8, 12, 19]


def small_map() -> OccupancyMap:
    """30 x 40 cells of 0.1 m, rotated origin; walls round the edge, an unknown patch, a pillar; rows differ so
    a flipped or transposed grid shows."""
    grid = np.zeros((30, 40), np.int8)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 100
    grid[20:25, 3:9] = -1
    grid[5:8, 30:32] = 100
    return OccupancyMap(grid, 0.1, origin_x=-1.5, origin_y=-0.75, origin_yaw=0.25)


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def make_stream(candidates: bool = True, frames: bool = True, agreement: bool = True) -> ReplayStream:
    rng = np.random.default_rng(7)
    stamps = 1_700_000_000.0 + 0.05 * np.arange(T) + rng.uniform(0, 0.004, T)
    odom = np.column_stack([np.cumsum(rng.uniform(0.02, 0.06, T)), np.cumsum(rng.normal(0, 0.01, T)),
                            wrap(np.cumsum(rng.normal(0.05, 0.1, T)) + 3.0)])
    pose = np.column_stack([odom[:, 0] * 0.9 + 0.7, odom[:, 1] - 0.4 + rng.normal(0, 0.02, T),
                            wrap(odom[:, 2] - 1.2 + rng.normal(0, 0.01, T))])
    a = rng.normal(size=(T, 3, 3))
    cov = a @ a.transpose(0, 2, 1) * 0.01  # symmetric positive definite, all cells distinct
    clouds = [rng.normal(pose[k], 0.1, size=(5 + k, 3)).astype(np.float32) if k in CLOUD_STEPS else None
              for k in range(T)]
    cand = [np.column_stack([rng.uniform(-1, 2, (3, 3)), [0.5, 0.3, 0.2]]) if k in CANDIDATE_STEPS else None
            for k in range(T)] if candidates else None
    frm = [((b"\xff\xd8\xff" + bytes([k]) * 40), "jpeg") if k % 8 else (b"\x89PNG\r\n\x1a\n" + bytes(30), "png")
           for k in range(T)] if frames else None
    if frm is not None:
        frm = [f if k in FRAME_STEPS else None for k, f in enumerate(frm)]
    agree = np.where(np.arange(T) == 3, np.nan, np.linspace(0.2, 0.9, T)) if agreement else None
    return ReplayStream(stamps=stamps, map=small_map(), odom=odom, base_from_laser=(0.2, -0.05, 0.1),
                        ranges=rng.uniform(0.5, 8.0, (T, BEAMS)).astype(np.float32), angle_min=-1.5,
                        angle_increment=0.2, range_min=0.08, range_max=12.0, pose=pose, cov=cov, state=STATES,
                        agreement=agree, clouds=clouds, candidates=cand, frames=frm, odom_frame="odom_r",
                        base_frame="base_r", laser_frame="laser_r")


def read_back(path: Path) -> tuple[dict, dict]:
    """(topic -> (type, latched), topic -> [(bag time s, msg)])."""
    from rosbags.interfaces import QosDurability

    conns, msgs = {}, {}
    with open_reader(path) as reader:
        for c in reader.connections:
            ext = c.ext
            latched = (bool(ext.latching) if hasattr(ext, "latching") else
                       any(q.durability == QosDurability.TRANSIENT_LOCAL for q in ext.offered_qos_profiles))
            conns[c.topic] = (c.msgtype, latched)
            msgs[c.topic] = []
        for c, t, raw in reader.messages():
            msgs[c.topic].append((t * 1e-9, reader.deserialize(raw, c.msgtype)))
    return conns, msgs


def yaw_of(q) -> float:
    assert abs(q.x) < 1e-12 and abs(q.y) < 1e-12
    return float(2 * np.arctan2(q.z, q.w))


def xyt(tr) -> np.ndarray:
    t = tr.transform.translation
    return np.array([t.x, t.y, yaw_of(tr.transform.rotation)])


def compose(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_replay_bag_holds_every_topic_and_the_localization(tmp_path, suffix):
    stream = make_stream()
    dst = write_replay_bag(tmp_path / f"replay{suffix}", stream)
    assert dst == tmp_path / f"replay{suffix}" and dst.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [dst.name]  # no temporary left behind
    conns, msgs = read_back(dst)
    n_states = 4
    expected = {
        "/map": ("nav_msgs/msg/OccupancyGrid", True, 1),
        "/tf_static": ("tf2_msgs/msg/TFMessage", True, 1),
        "/tf": ("tf2_msgs/msg/TFMessage", False, T),
        "/siteloc/scan": ("sensor_msgs/msg/LaserScan", False, T),
        "/siteloc/pose": ("geometry_msgs/msg/PoseWithCovarianceStamped", False, T),
        "/siteloc/particles": ("geometry_msgs/msg/PoseArray", False, len(CLOUD_STEPS)),
        "/siteloc/state": ("std_msgs/msg/String", False, n_states),
        "/siteloc/agreement": ("std_msgs/msg/Float32", False, T - 1),  # step 3 has NaN
        "/siteloc/candidates": ("geometry_msgs/msg/PoseArray", False, len(CANDIDATE_STEPS)),
        "/siteloc/camera/compressed": ("sensor_msgs/msg/CompressedImage", False, len(FRAME_STEPS)),
    }
    assert set(TOPICS.values()) == set(expected)
    assert {k: (*conns[k], len(msgs[k])) for k in conns} == expected
    s = stream.stamps

    # bag times and header stamps are the scans' stamps (microseconds kept)
    for topic in ("/siteloc/scan", "/siteloc/pose", "/tf"):
        bag_t = np.array([t for t, _ in msgs[topic]])
        assert np.allclose(bag_t, s, atol=1e-6, rtol=0)
        heads = [m.transforms[0] for _, m in msgs[topic]] if topic == "/tf" else [m for _, m in msgs[topic]]
        assert np.allclose([stamp_of(m) for m in heads], s, atol=1e-6, rtol=0)
    for topic, steps in (("/siteloc/particles", CLOUD_STEPS), ("/siteloc/candidates", CANDIDATE_STEPS),
                         ("/siteloc/camera/compressed", FRAME_STEPS)):
        assert np.allclose([stamp_of(m) for _, m in msgs[topic]], s[steps], atol=1e-6, rtol=0)
    assert np.allclose([t for t, _ in msgs["/map"] + msgs["/tf_static"]], s[0], atol=1e-6, rtol=0)
    all_t = [t for topic in msgs for t, _ in msgs[topic]]
    assert min(all_t) >= s[0] - 1e-6 and max(all_t) <= s[-1] + 1e-6

    # tf: map -> odom composed with odom -> base is the estimate; base -> laser is the mount
    for k, (_, m) in enumerate(msgs["/tf"]):
        by_child = {tr.child_frame_id: tr for tr in m.transforms}
        assert set(by_child) == {"odom_r", "base_r"}
        assert by_child["odom_r"].header.frame_id == "map" and by_child["base_r"].header.frame_id == "odom_r"
        odom = xyt(by_child["base_r"])
        assert np.allclose(odom[:2], stream.odom[k, :2], atol=1e-9) and abs(wrap(odom[2] - stream.odom[k, 2])) < 1e-9
        est = compose(xyt(by_child["odom_r"]), odom)
        assert np.allclose(est[:2], stream.pose[k, :2], atol=1e-9)
        assert abs(wrap(est[2] - stream.pose[k, 2])) < 1e-9
    (st,) = msgs["/tf_static"][0][1].transforms
    assert (st.header.frame_id, st.child_frame_id) == ("base_r", "laser_r")
    assert np.allclose(xyt(st), (0.2, -0.05, 0.1), atol=1e-12)

    # the estimate and its covariance at x, y, rot-z of the 6 x 6
    for k, (_, m) in enumerate(msgs["/siteloc/pose"]):
        assert m.header.frame_id == "map"
        p = m.pose.pose
        assert np.allclose([p.position.x, p.position.y, yaw_of(p.orientation)], stream.pose[k], atol=1e-9)
        c6 = np.asarray(m.pose.covariance).reshape(6, 6)
        assert np.allclose(c6[np.ix_([0, 1, 5], [0, 1, 5])], stream.cov[k])
        assert c6[0, 0] == m.pose.covariance[0] and c6[1, 5] == m.pose.covariance[11]
        assert m.pose.covariance[35] == stream.cov[k, 2, 2] and m.pose.covariance[5] == stream.cov[k, 0, 2]
        rest = np.ones((6, 6), bool)
        rest[np.ix_([0, 1, 5], [0, 1, 5])] = False
        assert not c6[rest].any()

    # the scan in the laser frame, as given
    for k, (_, m) in enumerate(msgs["/siteloc/scan"]):
        assert m.header.frame_id == "laser_r" and len(m.ranges) == BEAMS
        assert np.array_equal(np.asarray(m.ranges), stream.ranges[k])
        assert np.isclose(m.angle_min, -1.5) and np.isclose(m.angle_increment, 0.2)
        assert np.isclose(m.angle_max, -1.5 + 0.2 * (BEAMS - 1))
        assert np.isclose(m.range_min, 0.08) and np.isclose(m.range_max, 12.0)

    # particles, candidates (x, y, theta of the given), frames, state changes, agreement
    for (_, m), k in zip(msgs["/siteloc/particles"], CLOUD_STEPS, strict=True):
        got = np.array([[p.position.x, p.position.y, yaw_of(p.orientation)] for p in m.poses])
        assert m.header.frame_id == "map" and got.shape == stream.clouds[k].shape
        assert np.allclose(got[:, :2], stream.clouds[k][:, :2], atol=1e-6)
        assert np.allclose(wrap(got[:, 2] - stream.clouds[k][:, 2]), 0, atol=1e-6)
    for (_, m), k in zip(msgs["/siteloc/candidates"], CANDIDATE_STEPS, strict=True):
        got = np.array([[p.position.x, p.position.y, yaw_of(p.orientation)] for p in m.poses])
        assert np.allclose(got[:, :2], stream.candidates[k][:, :2]) and len(got) == 3
    for (_, m), k in zip(msgs["/siteloc/camera/compressed"], FRAME_STEPS, strict=True):
        data, kind = stream.frames[k]
        assert bytes(m.data) == data and m.format == kind and m.header.frame_id == "camera"
    assert [(m.data, t) for t, m in msgs["/siteloc/state"]] == [
        (STATES[k], pytest.approx(s[k], abs=1e-6)) for k in (0, 5, 13, 16)]
    agree = [(t, m.data) for t, m in msgs["/siteloc/agreement"]]
    keep = [k for k in range(T) if k != 3]
    assert np.allclose([a for _, a in agree], stream.agreement[keep], atol=1e-6)
    assert np.allclose([t for t, _ in agree], s[keep], atol=1e-6, rtol=0)


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_the_map_round_trips_through_the_recording_reader(tmp_path, suffix):
    from pipeline.rosbag.read import read_recording

    stream = make_stream(frames=False)  # a camera topic would need its CameraInfo to be read
    rec = read_recording(write_replay_bag(tmp_path / f"r{suffix}", stream))
    occ = stream.map
    assert rec.grid is not None and rec.grid.grid.dtype == np.int8
    assert np.array_equal(rec.grid.grid, occ.grid)  # row 0 the lowest y, both sides
    assert rec.grid.resolution == pytest.approx(occ.resolution)
    assert (rec.grid.origin_x, rec.grid.origin_y) == pytest.approx((occ.origin_x, occ.origin_y))
    assert rec.grid.origin_yaw == pytest.approx(occ.origin_yaw, abs=1e-9)
    assert rec.topics["scan"] == "/siteloc/scan" and rec.laser_frame == "laser_r"
    assert np.allclose(rec.scan_stamps, stream.stamps, atol=1e-6, rtol=0)
    # the cell a world point falls in is the same cell on both sides
    x, y = occ.cell_to_world(np.array([0, 6, 29]), np.array([0, 31, 39]))
    assert np.array_equal(rec.grid.value_at(x, y), occ.value_at(x, y))


def test_optional_topics_only_when_given(tmp_path):
    stream = make_stream(candidates=False, frames=False, agreement=False)
    conns, msgs = read_back(write_replay_bag(tmp_path / "plain.mcap", stream))
    assert "/siteloc/candidates" not in conns and "/siteloc/camera/compressed" not in conns
    assert "/siteloc/agreement" not in conns
    assert {"/map", "/tf", "/tf_static", "/siteloc/scan", "/siteloc/pose", "/siteloc/particles",
            "/siteloc/state"} == set(conns)
    all_none = dataclasses.replace(make_stream(), candidates=[None] * T, clouds=None)
    conns, _ = read_back(write_replay_bag(tmp_path / "none.bag", all_none))
    assert "/siteloc/candidates" not in conns and "/siteloc/particles" not in conns
    assert "/siteloc/camera/compressed" in conns


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_a_failure_midway_leaves_no_file_and_an_old_file_untouched(tmp_path, suffix, monkeypatch):
    from pipeline.rosbag.messages import Messages

    real = Messages.pose_array
    calls = []

    def failing(self, *a, **kw):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("injected")
        return real(self, *a, **kw)

    monkeypatch.setattr(Messages, "pose_array", failing)
    dst = tmp_path / f"replay{suffix}"
    with pytest.raises(RuntimeError, match="injected"):
        write_replay_bag(dst, make_stream())
    assert list(tmp_path.iterdir()) == []  # nothing at dst, the temporary folder removed
    dst.write_bytes(b"previous replay")
    calls.clear()
    with pytest.raises(RuntimeError, match="injected"):
        write_replay_bag(dst, make_stream())
    assert dst.read_bytes() == b"previous replay" and list(tmp_path.iterdir()) == [dst]
    monkeypatch.setattr(Messages, "pose_array", real)
    write_replay_bag(dst, make_stream())  # complete: replaces the old file
    assert dst.stat().st_size > 1000 and list(tmp_path.iterdir()) == [dst]


def test_format_choice_and_refusals(tmp_path):
    stream = make_stream(frames=False, candidates=False)
    p = write_replay_bag(tmp_path / "as_ros1.mcap", stream, fmt="bag")
    assert p.read_bytes()[:13] == b"#ROSBAG V2.0\n"
    p = write_replay_bag(tmp_path / "r.mcap", stream)
    assert p.read_bytes()[:8] == b"\x89MCAP0\r\n"
    with pytest.raises(ValueError, match="fmt"):
        write_replay_bag(tmp_path / "r.db3", stream, fmt="db3")
    (tmp_path / "folder.mcap").mkdir()
    with pytest.raises(IsADirectoryError):
        write_replay_bag(tmp_path / "folder.mcap", stream)
    assert list((tmp_path / "folder.mcap").iterdir()) == []


def test_stream_checks_its_arrays():
    good = make_stream()
    with pytest.raises(ValueError, match="non-decreasing"):
        dataclasses.replace(good, **{"stamps": good.stamps[::-1]})
    with pytest.raises(ValueError, match="pose"):
        dataclasses.replace(good, **{"pose": good.pose[:-1]})
    with pytest.raises(ValueError, match="unknown states"):
        dataclasses.replace(good, **{"state": ["tracking"] * (T - 1) + ["confused"]})
    with pytest.raises(ValueError, match=r"clouds\[2\]"):
        dataclasses.replace(good, **{"clouds": [None, None, np.zeros((3, 2))] + [None] * (T - 3)})
    with pytest.raises(ValueError, match="frames"):
        dataclasses.replace(good, **{"frames": [(b"x", "gif")] * T})
    assert good.ranges.dtype == np.float32 and good.stamps.dtype == np.float64 and good.steps == T


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_ordered_bag_writer_writes_at_once_and_refuses_going_back(tmp_path, fmt):
    from pipeline.rosbag.messages import STRING

    with BagWriter(tmp_path / ("o.bag" if fmt == "bag" else "o"), fmt, ordered=True) as w:
        w.topic("/a", STRING)
        w.write("/a", 1.0, w.msgs.string("one"))
        w.write("/a", 1.0, w.msgs.string("same time"))
        w.write("/a", 2.0, w.msgs.string("two"))
        assert w._pending == []  # nothing held back
        with pytest.raises(ValueError, match="time order"):
            w.write("/a", 1.5, w.msgs.string("back"))
    path = tmp_path / "o.bag" if fmt == "bag" else next((tmp_path / "o").glob("*.mcap"))
    _, msgs = read_back(path)
    assert [(t, m.data) for t, m in msgs["/a"]] == [(1.0, "one"), (1.0, "same time"), (2.0, "two")]


# ---------------------------------------------------------------- overview figure

def colour_mask(img: np.ndarray, hex_colour: str, tol: float = 40.0) -> np.ndarray:
    rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)], float)
    return np.linalg.norm(img[:, :, :3].astype(float) - rgb, axis=2) < tol


def open_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"))


def three_state_run(x0=1.0, y0=1.0, length=6.0):
    """A path left to right: tracking the first third, relocalising the second, lost the last."""
    n = 60
    x = x0 + np.linspace(0, length, n)
    pose = np.column_stack([x, y0 + 0.3 * np.sin(np.linspace(0, 3, n)), np.zeros(n)])
    states = ["tracking"] * 20 + ["relocalising"] * 20 + ["lost"] * 20
    return pose, states


def test_overview_shows_the_states_in_their_colours(tmp_path):
    from pipeline.evaluation.overview import OVERVIEW_COLOURS, overview_figure

    grid = np.zeros((60, 100), np.int8)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 100
    occ = OccupancyMap(grid, 0.08)  # 8 m x 4.8 m
    pose, states = three_state_run()
    gt = pose + [0.0, 0.15, 0.0]
    out = overview_figure(tmp_path / "o.png", occ, pose, states, gt=gt, converged_step=20, lost_steps=[40],
                          kidnapped_steps=[45], title="a run")
    assert out == tmp_path / "o.png" and out.is_file()
    img = open_png(out)
    h, w = img.shape[:2]
    assert 800 <= w <= 1300 and 350 <= h <= 900  # 8 in at 110 dpi, plus the legend beside the map
    assert list(tmp_path.iterdir()) == [out]
    cx = {}
    for state, colour in OVERVIEW_COLOURS.items():
        m = colour_mask(img, colour)
        m[:, int(0.8 * w):] = False  # the legend, beside the map on the right
        assert m.sum() > 200, state
        cx[state] = np.flatnonzero(m.any(axis=0)).mean()
    assert cx["tracking"] < cx["relocalising"] < cx["lost"]  # each colour where the path has that state


def test_overview_without_a_state_has_none_of_its_colour_on_the_map(tmp_path):
    from pipeline.evaluation.overview import OVERVIEW_COLOURS, overview_figure

    occ = OccupancyMap(np.zeros((60, 100), np.int8), 0.08)
    pose, _ = three_state_run()
    img = open_png(overview_figure(tmp_path / "t.png", occ, pose, ["tracking"] * len(pose)))
    w = img.shape[1]
    on_map = img[:, : int(0.8 * w)]
    assert colour_mask(on_map, OVERVIEW_COLOURS["tracking"]).sum() > 500
    assert colour_mask(on_map, OVERVIEW_COLOURS["lost"]).sum() == 0
    assert colour_mask(on_map, OVERVIEW_COLOURS["relocalising"]).sum() == 0


def test_overview_zooms_to_a_path_much_smaller_than_the_map(tmp_path):
    from pipeline.evaluation.overview import OVERVIEW_COLOURS, overview_figure

    res = 0.1
    big = OccupancyMap(np.zeros((400, 400), np.int8), res, origin_x=-20.0, origin_y=-20.0)  # 40 m; path 2 m
    pose, states = three_state_run(x0=5.0, y0=3.0, length=2.0)
    img = open_png(overview_figure(tmp_path / "z.png", big, pose, states))
    w = img.shape[1]
    path_px = np.zeros(img.shape[:2], bool)
    for colour in OVERVIEW_COLOURS.values():
        path_px |= colour_mask(img, colour)
    path_px[:, int(0.8 * w):] = False  # legend
    cols = np.flatnonzero(path_px.any(axis=0))
    assert cols.max() - cols.min() > 0.4 * w  # a 2 m path across most of the picture of a 40 m map


def test_overview_of_an_empty_and_a_one_step_run(tmp_path):
    from pipeline.evaluation.overview import overview_figure

    occ = OccupancyMap(np.zeros((20, 30), np.int8), 0.1)
    assert overview_figure(tmp_path / "e.png", occ, np.zeros((0, 3)), []).is_file()
    assert overview_figure(tmp_path / "one.png", occ, np.array([[1.0, 1.0, 0.0]]), ["lost"],
                           lost_steps=[0, 7]).is_file()
    with pytest.raises(ValueError, match="states"):
        overview_figure(tmp_path / "bad.png", occ, np.zeros((2, 3)), ["lost"])
