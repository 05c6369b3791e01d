"""Time in recordings: a camera clock offset and its correction, a tf drop-out, duplicate stamps.

The tiny site's `query_a` drive has 9 scans at 2 Hz (t = 0, 0.5, ... 4 s) with a frame at steps 0, 3 and
6, and map -> odom published at every scan; each case edits that bag and ingests it beside `capture`.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.rosbag.ingest import BagOptions, run_ingest_bag
from pipeline.rosbag.messages import stamp_of
from tests.rosbag.bags import exported, header_stamps, restamped, rewrite

CFG = load_config("demo")
CAMERA, INFO, SCAN = "/camera/image_raw/compressed", "/camera/camera_info", "/scan"
IMAGE_STEPS = [0, 3, 6]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(bags folder, baseline ingest of the unedited bags)."""
    root = tmp_path_factory.mktemp("sync")
    _, bags = exported(root)
    return bags, Ingested(run_ingest_bag(CFG, inputs={"bags": [bags]}, outputs={"out": root / "base"},
                                         progress=False))


@dataclasses.dataclass
class Ingested:
    out: object

    @property
    def report(self) -> dict:
        return json.loads((self.out / "bag_report.json").read_text())

    @property
    def dropped(self) -> dict:
        return self.report["recordings"]["query_a"]["dropped"]

    @property
    def rows(self) -> list[dict]:
        return list(csv.DictReader(io.StringIO((self.out / "runs" / "query_a" / "trajectory.csv").read_text())))

    def image_steps(self) -> list[int]:
        return [k for k, r in enumerate(self.rows) if r["image"]]

    def image_bytes(self) -> list[bytes]:
        return [(self.out / r["image"]).read_bytes() for r in self.rows if r["image"]]

    def captures(self) -> str:
        return (self.out / "captures.csv").read_text()


def ingest(tiny, tmp_path, edit, options: BagOptions | None = None, name: str = "out") -> Ingested:
    bags, _ = tiny
    query = rewrite(bags / "query_a", tmp_path / f"edited_{name}" / "query_a", edit)
    return Ingested(run_ingest_bag(CFG, inputs={"bags": [bags / "capture", query]}, outputs={"out": tmp_path / name},
                                   options=options, progress=False))


def camera_late(dt: float):
    """Every image's and camera_info's header stamp dt seconds late (the camera's clock is off)."""

    def edit(topic, msg, t, w):
        return [(topic, restamped(msg, w, dt) if topic in (CAMERA, INFO) else msg, t)]

    return edit


def test_baseline_has_the_fixture_images(tiny):
    _, base = tiny
    assert base.image_steps() == IMAGE_STEPS
    assert base.dropped["frames_without_scan"] == 0 and base.dropped["tf_gaps"] == []


def test_camera_clock_offset_without_and_with_correction(tiny, tmp_path):
    _, base = tiny
    late = ingest(tiny, tmp_path, camera_late(0.3), name="late")
    assert late.dropped["frames_without_scan"] == 3  # 0.2 s from the nearest scan: beyond the 0.05 s tolerance
    assert late.image_steps() == []
    assert late.report["runs"]["query_a"]["images"] == 0

    fixed = ingest(tiny, tmp_path, camera_late(0.3), BagOptions(offsets={"camera": -0.3, "camera_info": -0.3}),
                   name="fixed")
    assert fixed.dropped["frames_without_scan"] == 0
    assert fixed.image_steps() == IMAGE_STEPS
    assert fixed.image_bytes() == base.image_bytes()
    assert fixed.rows == base.rows
    # the offset applies to the capture drive too: its views are held 1 s, so the stops do not move
    assert fixed.captures() == base.captures()

    # CameraInfo stamps take no part in matching: the camera's own offset is enough
    camera_only = ingest(tiny, tmp_path, camera_late(0.3), BagOptions(offsets={"camera": -0.3}), name="cam")
    assert camera_only.image_steps() == IMAGE_STEPS and camera_only.dropped["frames_without_scan"] == 0


def test_camera_clock_offset_within_the_sync_tolerance_changes_nothing(tiny, tmp_path):
    _, base = tiny
    late = ingest(tiny, tmp_path, camera_late(0.02))
    assert late.dropped["frames_without_scan"] == 0
    assert late.rows == base.rows
    assert late.image_bytes() == base.image_bytes()


def test_wrong_correction_loses_the_frames(tiny, tmp_path):
    """A correction in the wrong direction doubles the offset: the check above could not pass by accident."""
    wrong = ingest(tiny, tmp_path, camera_late(0.3), BagOptions(offsets={"camera": 0.3}))
    assert wrong.image_steps() == [] and wrong.dropped["frames_without_scan"] == 3


def test_dropped_tf_interval(tiny, tmp_path):
    bags, base = tiny
    t0 = header_stamps(bags / "query_a", SCAN)[0]

    def no_localization(topic, msg, t, w):  # map -> odom missing at t0 + 1.5 and t0 + 2.0
        if topic == "/tf" and msg.transforms[0].header.frame_id == "map" and \
                1.25 < stamp_of(msg.transforms[0]) - t0 < 2.25:
            return []
        return [(topic, msg, t)]

    gap = ingest(tiny, tmp_path, no_localization)
    dropped = gap.dropped
    assert dropped["tf_gaps"] == [{"edge": "map -> odom", "from_s": 1.0, "to_s": 2.5, "gap_s": 1.5,
                                   "stamps_inside": 3}]  # the scans at 1.5 s and 2.0 s, the frame at 1.5 s
    assert dropped["scans_without_reference"] == 2
    assert dropped["frames_without_pose"] == 1
    assert dropped["scans_without_odometry"] == 0
    rows = gap.rows
    assert len(rows) == 9
    for k, (r, b) in enumerate(zip(rows, base.rows, strict=True)):
        gt = (r["gt_x"], r["gt_y"], r["gt_theta"])
        if k in (3, 4):
            assert gt == ("", "", ""), k
        else:
            assert gt == (b["gt_x"], b["gt_y"], b["gt_theta"]) and gt[0] != "", k
        assert (r["odom_x"], r["odom_y"], r["odom_theta"]) == (b["odom_x"], b["odom_y"], b["odom_theta"])
    md = (gap.out / "bag_report.md").read_text()
    assert "tf map -> odom has no message from 1.0 s to 2.5 s (1.5 s)" in md


def test_short_tf_drop_is_interpolated(tiny, tmp_path):
    """One missing map -> odom sample leaves a 1.0 s hole: within a 1.5 s --tf-max-gap it is interpolated."""
    bags, base = tiny
    t0 = header_stamps(bags / "query_a", SCAN)[0]

    def one_missing(topic, msg, t, w):
        if topic == "/tf" and msg.transforms[0].header.frame_id == "map" and \
                abs(stamp_of(msg.transforms[0]) - t0 - 1.5) < 0.01:
            return []
        return [(topic, msg, t)]

    strict = ingest(tiny, tmp_path, one_missing, name="strict")
    assert [g["stamps_inside"] for g in strict.dropped["tf_gaps"]] == [2]  # the scan and the frame at 1.5 s
    assert strict.rows[3]["gt_x"] == ""
    loose = ingest(tiny, tmp_path, one_missing, BagOptions(tf_max_gap_s=1.5), name="loose")
    assert loose.dropped["tf_gaps"] == [] and loose.dropped["scans_without_reference"] == 0
    # map -> odom is constant along the fixture's drive (odometry = ground truth - (1, 1.5)): interpolation is exact
    assert float(loose.rows[3]["gt_x"]) == pytest.approx(float(base.rows[3]["gt_x"]), abs=1e-9)


def test_duplicate_stamps_are_dropped_and_counted(tiny, tmp_path):
    bags, base = tiny
    seen = {SCAN: 0, CAMERA: 0}

    def repeated(topic, msg, t, w):
        out = [(topic, msg, t)]
        if topic in seen:
            k = seen[topic]
            seen[topic] += 1
            if topic == SCAN and k == 4:  # the same stamp again, other ranges: the first one is kept
                out.append((topic, dataclasses.replace(msg, ranges=np.ones(len(msg.ranges), np.float32)), t + 1e-3))
            if topic == CAMERA and k == 1:
                out.append((topic, msg, t + 1e-3))
        return out

    dup = ingest(tiny, tmp_path, repeated)
    assert dup.dropped["duplicate_stamps"] == 2
    rec = dup.report["recordings"]["query_a"]
    assert rec["scans"] == 9 and rec["frames"] == 3
    assert dup.report["runs"]["query_a"]["steps"] == 9
    assert dup.rows == base.rows
    assert np.array_equal(np.load(dup.out / "runs/query_a/scans.npy"), np.load(base.out / "runs/query_a/scans.npy"))
    assert dup.image_bytes() == base.image_bytes()


def test_a_silence_in_the_laser_stream_is_reported(tmp_path):
    """Scans 4 and 5 missing (1.5 s without a scan at 2 Hz): the report names the topic and the interval."""
    import json

    from pipeline.config import load_config
    from pipeline.rosbag.ingest import run_ingest_bag
    from tests.rosbag.bags import exported, rewrite

    _, bags = exported(tmp_path)
    n = {"scan": 0}

    def drop_two_scans(topic, msg, t, w):
        if topic == "/scan":
            n["scan"] += 1
            if n["scan"] in (5, 6):
                return []
        return [(topic, msg, t)]

    src = tmp_path / "in"
    src.mkdir()
    rewrite(bags / "query_a", src / "query_a", drop_two_scans)
    rewrite(bags / "capture", src / "capture", lambda topic, msg, t, w: [(topic, msg, t)])
    out = run_ingest_bag(load_config("demo"), inputs={"bags": [src]}, outputs={"out": tmp_path / "out"},
                         progress=False)
    rep = json.loads((out / "bag_report.json").read_text())["recordings"]
    assert rep["query_a"]["dropped"]["stream_gaps"] == [
        {"topic": "/scan", "from_s": 1.5, "to_s": 3.0, "gap_s": 1.5, "typical_period_s": 0.5}]
    assert rep["capture"]["dropped"]["stream_gaps"] == []  # no laser there
    assert "/scan is silent from 1.5 s to 3.0 s" in (out / "bag_report.md").read_text()
