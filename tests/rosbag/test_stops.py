"""Capture stops from camera frames: turns in place and stops every N metres, on synthetic arrays with
closed-form answers, and end to end on a generated continuous drive."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from PIL import Image

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.rosbag.bagfile import BagWriter
from pipeline.rosbag.export import OPTICAL
from pipeline.rosbag.ingest import BagOptions, run_ingest_bag
from pipeline.rosbag.messages import CAMERA_INFO, COMPRESSED, GRID, ODOMETRY, TF, yaw_quat
from pipeline.rosbag.stops import stops_every, turning_stops
from pipeline.runtime.motion import wrap_angle
from tests.fixtures.capture_site import H, W, floor_map

OFFSETS = np.radians([0.0, 60.0, 120.0, 180.0, 240.0, 300.0])
CFG = load_config("demo")


# --- turns in place -------------------------------------------------------------------------------------------


def turn(at, h0_deg: float, headings_deg, mount: float = 0.1):
    """Frames of a turn in place at `at`: base positions and camera poses (the camera `mount` m ahead)."""
    h = np.radians(h0_deg + np.asarray(headings_deg, dtype=np.float64))
    base = np.repeat(np.array([at], dtype=np.float64), len(h), axis=0)
    cam = np.column_stack([base[:, 0] + mount * np.cos(h), base[:, 1] + mount * np.sin(h), wrap_angle(h)])
    return base, cam


def drive(a, b, step: float = 0.1):
    """Frames driving straight from a to b (exclusive), camera along the way."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(round(np.hypot(*(b - a)) / step))
    base = a + (b - a) * (np.arange(1, n)[:, None] / n)
    cam = np.column_stack([base, np.full(len(base), math.atan2(*(b - a)[::-1]))])
    return base, cam


def test_turning_stops_closed_form():
    parts = [
        turn((1.0, 1.0), 17.0, np.arange(52) * 7.0),  # A: 0..357 deg counter-clockwise in 7 deg steps
        drive((1.0, 1.0), (3.0, 1.0)),
        turn((3.0, 1.0), 0.0, np.arange(21) * 10.0),  # B: only 200 deg
        drive((3.0, 1.0), (3.0, 2.5)),
        turn((3.0, 2.5), 0.0, [h for h in range(0, 360, 10) if not 95 < h < 145]),  # C: no frame near 120 deg
        drive((3.0, 2.5), (5.0, 1.0)),
        turn((5.0, 1.0), -40.0, -np.arange(52) * 7.0),  # D: clockwise
        drive((5.0, 1.0), (5.0, 3.0)),
        turn((5.0, 3.0), 0.0, [0, 10, 20, 30, 20, 10]),  # a wiggle, not a turn: not reported
    ]
    base = np.concatenate([p[0] for p in parts])
    cam = np.concatenate([p[1] for p in parts])
    starts = np.cumsum([0] + [len(p[0]) for p in parts])
    stamps = 100.0 + 0.1 * np.arange(len(base))
    tol = math.radians(5.0)
    stops, incomplete = turning_stops(stamps, base, cam, OFFSETS, radius=0.05, tolerance=tol)

    assert len(stops) == 2
    a, d = stops
    # A: view j is the frame nearest to 60 j degrees: k = round(60 j / 7), off by |7 k - 60 j| degrees
    k = [round(60 * j / 7) for j in range(6)]
    assert a.frames == [starts[0] + kk for kk in k] == [0, 9, 17, 26, 34, 43]
    assert a.heading_error == pytest.approx(math.radians(max(abs(7 * kk - 60 * j) for j, kk in enumerate(k))))
    assert a.heading_error == pytest.approx(math.radians(3.0))
    views = cam[a.frames, :2]
    assert a.spread == pytest.approx(np.max(np.hypot(*(views - views.mean(axis=0)).T)))
    assert a.spread == pytest.approx(0.1, abs=0.01)  # the camera circles 0.1 m around the standing base
    # D turns the other way: view j (+60 j) is reached after 360 - 60 j degrees
    kd = [0] + [round((360 - 60 * j) / 7) for j in range(1, 6)]
    assert d.frames == [starts[6] + kk for kk in kd]
    assert d.heading_error == pytest.approx(math.radians(3.0))

    assert [(i.at, i.stamp, i.missing_views) for i in incomplete] == [
        ((3.0, 1.0), pytest.approx(stamps[starts[2]]), [4, 5]),
        ((3.0, 2.5), pytest.approx(stamps[starts[4]]), [2]),
    ]
    assert incomplete[0].why == "turned 200 deg in place, a stop needs 295"
    assert incomplete[1].why == "no frame within 5.0 deg of these views"


def test_turning_stop_radius():
    """The base drifting 4 cm while turning is still one stop; 6 cm splits the turn into none."""
    for drift, n in ((0.04, 1), (0.06, 0)):
        base, cam = turn((1.0, 1.0), 0.0, np.arange(36) * 10.0)
        base = base + np.column_stack([np.linspace(0, drift, len(base)), np.zeros(len(base))])
        stops, inc = turning_stops(np.arange(len(base)) * 0.1, base, cam, OFFSETS, radius=0.05,
                                   tolerance=math.radians(5))
        assert len(stops) == n, drift
        if n == 1:
            assert stops[0].frames == [0, 6, 12, 18, 24, 30]


# --- a stop every N metres ------------------------------------------------------------------------------------


def test_stops_every_closed_form():
    """Frames every 0.1 m along x; the camera spins 60 deg per frame up to x = 3 m, then looks ahead (0 deg)."""
    n = 61
    x = 0.1 * np.arange(n)
    base = np.column_stack([x, np.zeros(n)])
    heading = np.where(np.arange(n) <= 30, np.radians(60.0 * (np.arange(n) % 6)), 0.0)
    cam = np.column_stack([base, wrap_angle(heading)])
    spacing, tol = 1.5, math.radians(15)
    stops, incomplete = stops_every(np.arange(n) * 0.2, base, cam, OFFSETS, spacing=spacing, tolerance=tol)

    # stops at 0, 1.5, 3.0 m (frames c = 0, 15, 30); the window |x - x_c| <= 0.75 m starts at frame lo = c - 7;
    # view k is the window's first frame of heading (c + k) mod 6 (ties go to the earliest frame)
    expected = []
    for c in (0, 15, 30):
        lo = max(0, c - 7)
        expected.append([lo + (c + k - lo) % 6 for k in range(6)])
    assert [s.frames for s in stops] == expected == [[0, 1, 2, 3, 4, 5], [9, 10, 11, 12, 13, 8],
                                                     [24, 25, 26, 27, 28, 23]]
    for s in stops:
        assert s.heading_error == pytest.approx(0.0, abs=1e-9)
        xs = x[s.frames]
        assert s.spread == pytest.approx(np.max(np.abs(xs - xs.mean())))
    assert [s.spread for s in stops] == pytest.approx([0.25, 0.25, 0.25])  # views 0.5 m apart
    # at 4.5 and 6.0 m the camera only looked ahead: every view but the first is missing
    assert [(i.at, i.stamp, i.missing_views) for i in incomplete] == [
        (pytest.approx((4.5, 0.0)), pytest.approx(45 * 0.2), [1, 2, 3, 4, 5]),
        (pytest.approx((6.0, 0.0)), pytest.approx(60 * 0.2), [1, 2, 3, 4, 5])]
    assert all("looks within 15 deg" in i.why for i in incomplete)


def test_stops_every_never_uses_one_frame_twice():
    x = 0.1 * np.arange(11)
    base = np.column_stack([x, np.zeros(11)])
    cam = np.column_stack([base, np.zeros(11)])
    stops, incomplete = stops_every(x, base, cam, OFFSETS, spacing=1.0, tolerance=math.pi)
    assert stops == []
    assert [(i.at, i.missing_views, i.why) for i in incomplete] == [
        ((0.0, 0.0), [], "one frame would serve two views"), (pytest.approx((1.0, 0.0)), [],
                                                              "one frame would serve two views")]
    assert stops_every(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 3)), OFFSETS, spacing=1.0, tolerance=0.1) == ([],
                                                                                                               [])


# --- a generated continuous drive -----------------------------------------------------------------------------

CENTRE, RADIUS = np.array([1.5, 2.0]), 0.9  # a circle in room A (x < 3 m) ...
LOOP = 0.2  # ... with one full loop of this radius at its top, inside the circle
ARC = RADIUS * math.pi  # the drive reaches the top of the circle after this many metres
LOOP_CENTRE = CENTRE + np.array([0.0, RADIUS - LOOP])
LENGTH = 2 * ARC + 2 * math.pi * LOOP
SPEED = 0.5
MAP_FROM_ODOM = (0.2, -0.1, 0.05)


def path_pose(s: np.ndarray) -> np.ndarray:
    """map_from_base (x, y, heading) after s metres: counter-clockwise round the circle from its bottom,
    a counter-clockwise loop at the top, then the rest of the circle back to the start."""
    s = np.asarray(s, dtype=np.float64)
    out = np.zeros((len(s), 3))
    loop_end = ARC + 2 * math.pi * LOOP
    on_loop = (s >= ARC) & (s < loop_end)
    phi = np.where(s < ARC, -math.pi / 2 + s / RADIUS, math.pi / 2 + (s - loop_end) / RADIUS)
    out[:, 0] = CENTRE[0] + RADIUS * np.cos(phi)
    out[:, 1] = CENTRE[1] + RADIUS * np.sin(phi)
    out[:, 2] = phi + math.pi / 2
    u = (s - ARC) / LOOP
    out[on_loop, 0] = LOOP_CENTRE[0] + LOOP * np.cos(math.pi / 2 + u[on_loop])
    out[on_loop, 1] = LOOP_CENTRE[1] + LOOP * np.sin(math.pi / 2 + u[on_loop])
    out[on_loop, 2] = math.pi + u[on_loop]
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def se2_inv_compose(a, b: np.ndarray) -> np.ndarray:
    """inv(a) * b for one SE(2) pose a and poses b (N, 3)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[:, 0] - a[0], b[:, 1] - a[1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[2])])


def png(k: int) -> bytes:
    px = np.zeros((H, W, 3), np.uint8) + np.array([(13 * k) % 256, (7 * k) % 256, 90], np.uint8)
    buf = io.BytesIO()
    Image.fromarray(px).save(buf, format="PNG")
    return buf.getvalue()


def write_drive(path, fmt: str = "mcap"):
    from scipy.spatial.transform import Rotation

    t0 = 1_700_100_000.0
    odom_t = np.arange(0.0, LENGTH / SPEED, 0.05)
    frame_t = np.arange(0.0, LENGTH / SPEED, 0.1)
    occ = floor_map()
    with BagWriter(path, fmt) as w:
        m = w.msgs
        for name, typename in (("/tf_static", TF), ("/map", GRID), ("/tf", TF), ("/odom", ODOMETRY),
                               ("/camera/image_raw/compressed", COMPRESSED), ("/camera/camera_info", CAMERA_INFO)):
            w.topic(name, typename, latched=name in ("/tf_static", "/map"))
        w.write("/tf_static", t0, m.tf([m.transform_stamped(t0, "base_link", "camera_optical_frame", (0.0, 0.0, 1.2),
                                                            tuple(Rotation.from_matrix(OPTICAL).as_quat()))]))
        w.write("/map", t0, m.occupancy_grid(t0, occ.grid, occ.resolution, (occ.origin_x, occ.origin_y, 0.0)))
        odom = se2_inv_compose(MAP_FROM_ODOM, path_pose(SPEED * odom_t))
        for i, (t, pose) in enumerate(zip(t0 + odom_t, odom, strict=True)):
            w.write("/odom", t + 0.002, m.odometry(t, pose, seq=i))
            w.write("/tf", t + 0.002, m.tf([m.transform_stamped(t, "map", "odom", (*MAP_FROM_ODOM[:2], 0.0),
                                                                yaw_quat(MAP_FROM_ODOM[2]))]))
        for k, t in enumerate(t0 + frame_t):
            w.write("/camera/image_raw/compressed", t + 0.03,
                    m.compressed_image(t, "camera_optical_frame", png(k), "png", seq=k))
            w.write("/camera/camera_info", t + 0.03,
                    m.camera_info(t, "camera_optical_frame", W, H, 40.0, 40.0, 32.0, 24.0, seq=k))
    return path, frame_t


@pytest.fixture(scope="module")
def drive_bag(tmp_path_factory):
    return write_drive(tmp_path_factory.mktemp("drive") / "loop")


def test_continuous_drive_stops_every(drive_bag, tmp_path):
    bag, frame_t = drive_bag
    spacing = 1.0
    out = run_ingest_bag(CFG, inputs={"bags": [bag]}, outputs={"out": tmp_path / "out"},
                         options=BagOptions(stops="every", stops_every_m=spacing), progress=False)
    rep = json.loads((out / "bag_report.json").read_text())
    rec = rep["recordings"]["loop"]
    assert rec["frames"] == len(frame_t) and rec["dropped"]["frames_without_pose"] == 0
    # one place per metre driven: 0 .. 6 m; only on the small loop (2.83 .. 4.08 m) does the camera look every way
    places = int(SPEED * frame_t[-1] // spacing) + 1
    assert places == 7
    assert rep["stops"] == 2 and rec["stops"] == 2
    inc = rec["incomplete_stops"]
    assert len(inc) == places - 2
    assert [i["t"] for i in inc] == pytest.approx([0.0, 2.0, 4.0, 10.0, 12.0])  # metres / SPEED
    expected_at = path_pose(np.array([0.0, 1.0, 2.0, 5.0, 6.0]))
    for i, e in zip(inc, expected_at, strict=True):
        assert np.hypot(i["at"][0] - e[0], i["at"][1] - e[1]) < 0.05, (i, e)  # the frames' chords: a little short
        assert i["missing_views"] == [1, 2, 3, 4, 5]  # within 0.5 m of the circle: headings only +-32 deg
        assert "looks within 15 deg" in i["why"]

    rows = list(csv.DictReader(io.StringIO((out / "captures.csv").read_text())))
    assert len(rows) == 12
    by_stop: dict[str, list[dict]] = {}
    for r in rows:
        by_stop.setdefault(r["stop_id"], []).append(r)
    assert sorted(by_stop) == ["stop0000", "stop0001"]
    tol = 15.0
    for views in by_stop.values():
        assert [int(v["view"]) for v in views] == list(range(6))
        xy = np.array([[float(v["x"]), float(v["y"])] for v in views])
        th = np.array([float(v["theta"]) for v in views])
        # view 0 is the stop's own frame: on the small loop (the camera sits above the base)
        assert abs(np.hypot(*(xy[0] - LOOP_CENTRE)) - LOOP) < 1e-3
        # every view within the window (spacing / 2) of it, looking within the tolerance of its rig heading
        assert np.all(np.hypot(*(xy - xy[0]).T) <= spacing / 2 + 1e-6)
        err = np.degrees(np.abs(wrap_angle(th - th[0] - OFFSETS)))
        assert err.max() <= 7.5  # the loop's frames are 14.3 deg apart: the nearest is within half of that
        assert err.max() <= tol
        # each view's pose is the path's at its frame: the same image as the frame written at that time
        for v in views:
            data = (out / v["image"]).read_bytes()
            k = next(k for k in range(len(frame_t)) if png(k) == data)
            p = path_pose(np.array([SPEED * frame_t[k]]))[0]
            assert (float(v["x"]), float(v["y"])) == pytest.approx((p[0], p[1]), abs=2e-6)
            assert abs(wrap_angle(float(v["theta"]) - p[2])) < 2e-6  # captures.csv keeps 6 decimals
    assert "ingest.position_tolerance_m" in rep["ingest_needs"]  # views 0.4 m apart: a weaker capture
    assert rep["runs"] == {}


def test_continuous_drive_has_no_turns(drive_bag, tmp_path):
    bag, _ = drive_bag
    with pytest.raises(InputError) as info:
        run_ingest_bag(CFG, inputs={"bags": [bag]}, outputs={"out": tmp_path / "out"},
                       options=BagOptions(stops="turns"), progress=False)
    assert "no capture stops" in str(info.value) and "--stops every" in str(info.value)
    assert not (tmp_path / "out").exists()
