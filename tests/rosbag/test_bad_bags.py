"""Broken recordings: each raises one InputError that names the problem (and the topic), and leaves nothing behind.

Every case starts from the tiny site's exported bags and breaks one thing: the capture drive is passed
unchanged beside the broken `query_a` drive, so the error must come from the broken part.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.io.map_yaml import FREE, OccupancyMap, write_map
from pipeline.rosbag.ingest import BagOptions, run_ingest_bag
from pipeline.rosbag.messages import COMPRESSED, IMAGE, stamp_of
from tests.rosbag.bags import exported, header_stamps, restamped, rewrite, truncated

CFG = load_config("demo")
CAMERA, INFO, SCAN = "/camera/image_raw/compressed", "/camera/camera_info", "/scan"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Exported bags of the tiny site, by format (each format exported once, when first asked for)."""
    root = tmp_path_factory.mktemp("tiny")
    cache: dict[str, object] = {}

    def get(fmt: str = "mcap"):
        if fmt not in cache:
            cache[fmt] = exported(root / fmt, fmt)[1]
        return cache[fmt]

    return get


def fails(tmp_path, bags, *parts: str, options: BagOptions | None = None, **inputs) -> str:
    """run_ingest_bag raises InputError whose text holds every one of `parts`; no output, no temporaries."""
    out = tmp_path / "out"
    with pytest.raises(InputError) as info:
        run_ingest_bag(CFG, inputs={"bags": bags, **inputs}, outputs={"out": out}, options=options, progress=False)
    text = str(info.value)
    for part in parts:
        assert part in text, f"{part!r} not in:\n{text}"
    assert "Traceback" not in text
    assert not out.exists()
    assert not list(tmp_path.glob(".out.tmp-*")), "a temporary output was left behind"
    return text


def broken(tiny, tmp_path, edit, **kw):
    """[capture, query_a with `edit` applied] (see bags.rewrite)."""
    bags = tiny()
    return [bags / "capture", rewrite(bags / "query_a", tmp_path / "broken" / "query_a", edit, **kw)]


def only(topic_name, change):
    """An edit that applies change(msg, index, w) -> msg to the messages of one topic."""
    seen = {"n": 0}

    def edit(topic, msg, t, w):
        if topic != topic_name:
            return [(topic, msg, t)]
        k = seen["n"]
        seen["n"] += 1
        return [(topic, change(msg, k, w), t)]

    return edit


# --- files that are not (complete) recordings ------------------------------------------------------------------


def test_truncated_mcap_inside_a_ros2_folder(tiny, tmp_path):
    bag = truncated(tiny("mcap") / "query_a", tmp_path / "cut" / "query_a")
    fails(tmp_path, [tiny() / "capture", bag], f"{bag}: cannot read the recording", "unreadable or truncated",
          "reindex")


def test_truncated_bare_mcap_file(tiny, tmp_path):
    bag = truncated(tiny("mcap") / "query_a" / "query_a.mcap", tmp_path / "cut" / "query_a.mcap", 0.3)
    fails(tmp_path, [bag], f"{bag}: cannot read the recording", "unreadable or truncated")


def test_truncated_ros1_bag(tiny, tmp_path):
    bag = truncated(tiny("bag") / "query_a.bag", tmp_path / "cut" / "query_a.bag")
    fails(tmp_path, [tiny("bag") / "capture.bag", bag], f"{bag}: cannot read the recording",
          "unreadable or truncated")


@pytest.mark.parametrize("fraction", [0.5, 0.99])
def test_truncated_sqlite_bag(tiny, tmp_path, fraction):
    """Cut early, sqlite refuses to open it; cut near the end it opens and breaks off while reading."""
    bag = truncated(tiny("db3") / "query_a", tmp_path / "cut" / "query_a", fraction)
    fails(tmp_path, [bag], f"{bag}", "truncated", "database disk image is malformed")


def test_a_file_that_is_not_a_bag(tmp_path):
    junk = tmp_path / "notes.bag"
    junk.write_text("these are my notes, not a recording\n")
    fails(tmp_path, [junk], f"{junk}: cannot read the recording", "unreadable or truncated")
    other = tmp_path / "notes.txt"
    other.write_text("hello\n")
    fails(tmp_path, [other], f"{other}: not a recording", "is not a recording", "metadata.yaml")
    empty = tmp_path / "empty"
    empty.mkdir()
    fails(tmp_path, [empty], f"{empty}: no recordings", "holds no .bag")


# --- topics ---------------------------------------------------------------------------------------------------


def test_no_camera_and_no_laser_topic(tiny, tmp_path):
    bags = broken(tiny, tmp_path, lambda topic, msg, t, w: [(topic, msg, t)], drop_topics=(CAMERA, INFO, SCAN))
    fails(tmp_path, bags, "has no camera (sensor_msgs/Image or CompressedImage) and no LaserScan topic", "--list")


def test_images_without_camera_info(tiny, tmp_path):
    bags = broken(tiny, tmp_path, lambda topic, msg, t, w: [(topic, msg, t)], drop_topics=(INFO,))
    fails(tmp_path, bags, f"query_a {CAMERA}: has images but no sensor_msgs/CameraInfo topic")


def test_two_image_topics_without_a_choice(tiny, tmp_path):
    def edit(topic, msg, t, w):
        out = [(topic, msg, t)]
        if topic == CAMERA:
            out.append(("/camera2/image_raw/compressed", msg, t))
        return out

    bags = broken(tiny, tmp_path, edit, extra_topics={"/camera2/image_raw/compressed": COMPRESSED})
    fails(tmp_path, bags, f"several camera topics: ['{CAMERA}', '/camera2/image_raw/compressed']",
          "--topic camera=NAME")


def test_topic_choice_naming_a_missing_topic(tiny, tmp_path):
    fails(tmp_path, [tiny()], "/front/image_raw", "--topic camera=/front/image_raw: no such topic",
          f"'{CAMERA}'", options=BagOptions(roles={"camera": "/front/image_raw"}))


def test_topic_choice_of_the_wrong_type(tiny, tmp_path):
    fails(tmp_path, [tiny() / "query_a"], f"{SCAN}: is sensor_msgs/msg/LaserScan, a camera topic must be one of",
          options=BagOptions(roles={"camera": SCAN}))


# --- camera ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("model", "d"), [("equidistant", [0.1, -0.05, 0.0, 0.0]),
                                          ("rational_polynomial", [0.1, -0.05, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0])])
def test_camera_info_with_a_distortion_that_is_not_plumb_bob(tiny, tmp_path, model, d):
    def distort(msg, k, w):
        return dataclasses.replace(msg, distortion_model=model, d=np.array(d))

    bags = broken(tiny, tmp_path, only(INFO, distort))
    fails(tmp_path, bags, f"{INFO} message 0", f"distortion model '{model}' with D={d}", "siteloc reads plumb_bob",
          "image_rect")


def test_a_distortion_in_one_recording_only_is_a_camera_mismatch(tiny, tmp_path):
    def distort(msg, k, w):
        return dataclasses.replace(msg, d=np.array([0.1, -0.05, 0.0, 0.0, 0.0]))

    bags = broken(tiny, tmp_path, only(INFO, distort))
    fails(tmp_path, bags, "recordings disagree on the camera", "coeffs=(0.1, -0.05, 0.0, 0.0, 0.0)")


def test_camera_info_size_differs_from_the_images(tiny, tmp_path):
    def wider(msg, k, w):
        return dataclasses.replace(msg, width=80)

    bags = broken(tiny, tmp_path, only(INFO, wider))
    fails(tmp_path, bags, f"{CAMERA} message 0", "image is 64x48, CameraInfo says 80x48")


def test_camera_info_without_an_image_size(tiny, tmp_path):
    def unsized(msg, k, w):
        return dataclasses.replace(msg, width=0, height=0)

    bags = broken(tiny, tmp_path, only(INFO, unsized))
    fails(tmp_path, bags, f"{INFO} message 0", "CameraInfo says the image is 0x0")


def test_intrinsics_change_mid_recording(tiny, tmp_path):
    def recalibrated(msg, k, w):
        if k < 1:
            return msg
        kk = np.array(msg.k, dtype=np.float64)
        kk[0] = 50.0
        return dataclasses.replace(msg, k=kk)

    bags = broken(tiny, tmp_path, only(INFO, recalibrated))
    text = fails(tmp_path, bags, f"{INFO} message 1", "intrinsics change", "fx=50.0", "(message 0)")
    assert "fx=40.0" in text


def test_raw_image_with_an_unsupported_encoding(tiny, tmp_path):
    def depth(topic, msg, t, w):
        if topic != CAMERA:
            return [(topic, msg, t)]
        img = w.msgs.raw_image(stamp_of(msg), msg.header.frame_id, np.zeros((48, 128), np.uint8), "16UC1")
        return [("/camera/image_raw", dataclasses.replace(img, width=64, step=128), t)]

    bags = broken(tiny, tmp_path, depth, extra_topics={"/camera/image_raw": IMAGE}, drop_topics=(CAMERA,))
    fails(tmp_path, bags, "/camera/image_raw message 0", "image encoding '16UC1' is not supported",
          "rgb8, bgr8, mono8, jpeg, png")


def test_compressed_image_that_is_neither_jpeg_nor_png(tiny, tmp_path):
    gif = b"GIF89a" + bytes(200)

    def as_gif(msg, k, w):
        return dataclasses.replace(msg, format="gif", data=np.frombuffer(gif, np.uint8))

    bags = broken(tiny, tmp_path, only(CAMERA, as_gif))
    fails(tmp_path, bags, f"{CAMERA} message 0", "neither JPEG nor PNG", "'gif'", "rgb8, bgr8, mono8, jpeg, png")


def test_compressed_image_with_a_damaged_png(tiny, tmp_path):
    """PNG signature, then garbage: the frame cannot be decoded (a PIL error must not escape)."""

    def damaged(msg, k, w):
        data = bytes(msg.data)
        if k == 1:
            data = data[:8] + bytes(len(data) - 8)
        return dataclasses.replace(msg, data=np.frombuffer(data, np.uint8))

    bags = broken(tiny, tmp_path, only(CAMERA, damaged))
    fails(tmp_path, bags, f"{CAMERA} message 1", "PNG image data cannot be decoded")


# --- laser ----------------------------------------------------------------------------------------------------


def test_scan_stamps_going_backwards(tiny, tmp_path):
    stamps = header_stamps(tiny() / "query_a", SCAN)

    def back(msg, k, w):
        return restamped(msg, w, stamps[3] - stamps[5]) if k == 5 else msg

    bags = broken(tiny, tmp_path, only(SCAN, back))
    fails(tmp_path, bags, f"{SCAN} message 5", "stamps out of order", f"{stamps[3]:.6f} s after {stamps[4]:.6f} s")


def test_scan_geometry_changing(tiny, tmp_path):
    def fewer(msg, k, w):
        return dataclasses.replace(msg, ranges=np.asarray(msg.ranges)[:45]) if k == 4 else msg

    bags = broken(tiny, tmp_path, only(SCAN, fewer))
    fails(tmp_path, bags, f"{SCAN} message 4", "scan geometry changes", "45 beams from -135.00 to -3.00 deg",
          "the first scan has 91")


# --- tf -------------------------------------------------------------------------------------------------------


def _without(pred):
    """Drop the transforms for which pred(transform) holds (and /tf messages left empty)."""

    def edit(topic, msg, t, w):
        if topic not in ("/tf", "/tf_static"):
            return [(topic, msg, t)]
        kept = [tr for tr in msg.transforms if not pred(tr)]
        return [(topic, w.msgs.tf(kept), t)] if kept else []

    return edit


def test_tf_without_map_to_odom_gives_a_run_without_reference(tiny, tmp_path):
    """A drive with no localization in it (what a robot records): its run has odometry and scans, no ground
    truth, and the report says so; its frames have no pose, so they make no stops."""
    import json

    from pipeline.errors import Problems
    from pipeline.io.capture_runs import read_run

    bags = broken(tiny, tmp_path, _without(lambda tr: tr.header.frame_id == "map"))
    out = run_ingest_bag(CFG, inputs={"bags": bags}, outputs={"out": tmp_path / "out"}, progress=False)
    rep = json.loads((out / "bag_report.json").read_text())["recordings"]
    assert rep["query_a"]["reference"] is False and rep["capture"]["reference"] is True
    assert rep["query_a"]["dropped"]["frames_without_pose"] == rep["query_a"]["frames"] > 0
    assert "no reference (no map frame in tf)" in (out / "bag_report.md").read_text()
    run = read_run(out / "runs" / "query_a", out, None, None, Problems())
    assert run.gt.shape[0] == rep["query_a"]["scans"] and np.isnan(run.gt).all()
    assert np.isfinite(run.odom).all()


def test_tf_with_map_attached_elsewhere(tiny, tmp_path):
    """A reference frame named with --frame must connect to the base; the tree is shown."""

    def elsewhere(topic, msg, t, w):
        if topic != "/tf":
            return [(topic, msg, t)]
        trs = [dataclasses.replace(tr, child_frame_id="odom_old") if tr.header.frame_id == "map" else tr
               for tr in msg.transforms]
        return [(topic, w.msgs.tf(trs), t)]

    bags = broken(tiny, tmp_path, elsewhere)
    fails(tmp_path, bags, "--frame map=map: not connected to 'base_link'", "map -> odom_old", "odom -> base_link",
          options=BagOptions(frames={"map": "map"}))


def test_camera_frame_missing_from_tf_static(tiny, tmp_path):
    bags = broken(tiny, tmp_path, _without(lambda tr: tr.child_frame_id == "camera_optical_frame"))
    fails(tmp_path, bags, "the camera is not in the tf tree", "/tf_static",
          "no transform between 'base_link' and the camera frame 'camera_optical_frame'")


def test_frame_with_two_parents(tiny, tmp_path):
    def second_parent(topic, msg, t, w):
        out = [(topic, msg, t)]
        if topic == "/tf" and msg.transforms[0].header.frame_id == "map":
            tr = msg.transforms[0]
            out.append((topic, w.msgs.tf([dataclasses.replace(tr, header=dataclasses.replace(
                tr.header, frame_id="world"))]), t))
        return out

    bags = broken(tiny, tmp_path, second_parent)
    fails(tmp_path, bags, "/tf message", "frame 'odom' has two parents, 'map' and 'world'")


# --- map, stops, other inputs ---------------------------------------------------------------------------------


def test_no_map_topic_and_no_map_argument(tiny, tmp_path):
    bags = tiny()
    nomap = [rewrite(bags / name, tmp_path / "nomap" / name, lambda topic, msg, t, w: [(topic, msg, t)],
                     drop_topics=("/map",)) for name in ("capture", "query_a")]
    fails(tmp_path, nomap, "no nav_msgs/OccupancyGrid topic in any recording", "--map map.yaml")
    site_map = bags.parent / "site" / "map.yaml"
    out = run_ingest_bag(CFG, inputs={"bags": nomap, "map": site_map}, outputs={"out": tmp_path / "ok"},
                         progress=False)
    assert (out / "map.yaml").is_file()  # the map argument is all that was missing


def test_no_complete_stop(tiny, tmp_path):
    """The query drive alone: frames, but no turn in place anywhere."""
    fails(tmp_path, [tiny() / "query_a"], "no capture stops", "query_a: 0 incomplete stops, none complete",
          "--stops every")


def test_map_argument_that_misses_the_stops(tiny, tmp_path):
    """The stops are checked in the written directory: the error names the output, never the temporary."""
    small = write_map(tmp_path / "small" / "map.yaml", OccupancyMap(np.full((20, 20), FREE, np.int8), 0.05))
    out = tmp_path / "out"
    text = fails(tmp_path, [tiny()], "is outside the map", map=small)
    assert ".tmp-" not in text and str(out / "captures.csv") in text


def test_missing_annotations_file(tiny, tmp_path):
    fails(tmp_path, [tiny()], "annotations", str(tmp_path / "nope.json"), "not found",
          annotations=tmp_path / "nope.json")


def test_annotations_that_are_not_json(tiny, tmp_path):
    """Read inside the output's temporary directory: the error is still an InputError and the temporary goes."""
    bad = tmp_path / "annotations.json"
    bad.write_text("{'images': [")
    fails(tmp_path, [tiny()], f"{bad}: annotations are not JSON", annotations=bad)


def test_stops_from_an_unknown_recording(tiny, tmp_path):
    fails(tmp_path, [tiny()], "--stops-from names no recording", "no recording named 'mapping'",
          options=BagOptions(stops_from=["mapping"]))


def test_good_bags_pass(tiny, tmp_path):
    """The unbroken input of every case above ingests (so each failure is the break's)."""
    bags = tiny()
    edit = rewrite(bags / "query_a", tmp_path / "same" / "query_a", lambda topic, msg, t, w: [(topic, msg, t)])
    out = run_ingest_bag(CFG, inputs={"bags": [bags / "capture", edit]}, outputs={"out": tmp_path / "out"},
                         progress=False)
    assert (out / "bag_report.json").is_file()
    assert header_stamps(edit, SCAN) == header_stamps(bags / "query_a", SCAN)
