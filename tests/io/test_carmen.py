"""CARMEN log parsing: synthetic logs with known content, malformed lines, and the five real logs."""

from __future__ import annotations

import gzip
import math

import numpy as np
import pytest

from pipeline.config import LaserLogConfig
from pipeline.errors import InputError
from pipeline.io.carmen import MAX_LISTED, flaser_geometry, read_carmen
from tests.fixtures.carmen_logs import flaser_line, require_carmen_dir, room_log_lines, room_poses, write_log


def _rl1_line(ranges, laser_pose, robot_pose, t, start=-1.0, fov=2.0, res=0.5, max_range=8.0) -> str:
    rem = "2 0.1 0.2"
    body = " ".join(str(r) for r in ranges)
    lx, ly, lt = laser_pose
    rx, ry, rt = robot_pose
    return (
        f"ROBOTLASER1 0 {start} {fov} {res} {max_range} 0.01 0 {len(ranges)} {body} {rem} "
        f"{lx} {ly} {lt} {rx} {ry} {rt} 0.1 0.0 0.5 0.2 0.3 {t} host {t}"
    )


@pytest.mark.parametrize("suffix", [".log", ".log.gz"])
def test_room_log_is_read_exactly(tmp_path, suffix):
    path = write_log(tmp_path / f"room{suffix}", room_log_lines(n_scans=12, n_beams=181, no_return_every=10))
    log = read_carmen(path)
    assert (log.n_scans, log.n_beams) == (12, 181)
    assert log.message_counts == {"#": 1, "FLASER": 12, "ODOM": 12, "PARAM": 1} and log.unknown_messages == []
    np.testing.assert_allclose(log.poses, room_poses(12), atol=1e-6)
    assert log.angle_min == pytest.approx(-math.pi / 2)
    assert log.angle_increment == pytest.approx(math.pi / 180)
    assert log.time_source == "log"
    np.testing.assert_allclose(log.t, 1.0 + np.arange(12))
    # FLASER lines are lines 2 + 2k + 2 (comment, PARAM, then ODOM/FLASER pairs), 1-based.
    np.testing.assert_array_equal(log.line_numbers, 4 + 2 * np.arange(12))
    assert log.ranges.dtype == np.float32
    # Every 10th beam carried the 81.83 code: it is stored as exactly range_max, nothing else is.
    no_ret = log.ranges >= log.range_max
    assert no_ret[:, ::10].all() and no_ret.sum() == 12 * len(range(0, 181, 10)) == log.no_return_count
    assert (log.ranges[no_ret] == np.float32(40.0)).all()


@pytest.mark.parametrize(
    ("n", "increment_deg", "last_deg"),
    [(180, 1.0, 89.0), (181, 1.0, 90.0), (360, 0.5, 89.5), (361, 0.5, 90.0)],
)
def test_flaser_beam_conventions(n, increment_deg, last_deg):
    angle_min, inc = flaser_geometry(n)
    assert math.degrees(angle_min) == pytest.approx(-90.0)
    assert math.degrees(inc) == pytest.approx(increment_deg)
    assert math.degrees(angle_min + (n - 1) * inc) == pytest.approx(last_deg)


def test_no_return_codes_and_long_readings(tmp_path):
    cfg = LaserLogConfig(no_return_ranges=(81.83, 50.0), range_max=30.0)
    ranges = [1.0, 81.83, 81.834, 50.0, 49.99, 31.0, 0.0, 29.99, 81.9]
    log = read_carmen(write_log(tmp_path / "a.log", [flaser_line(ranges, (0, 0, 0), 1.0)]), cfg)
    expected = np.float32([1.0, 30, 30, 30, 30, 30, 30, 29.99, 30])  # 49.99 is not a code but > range_max
    np.testing.assert_array_equal(log.ranges[0], expected)


def test_robotlaser1_uses_laser_pose_and_message_geometry(tmp_path):
    lines = [
        _rl1_line([1.0, 2.0, 8.0, 3.0, 4.0], (1.0, 2.0, 0.5), (0.8, 2.0, 0.5), 10.0),
        _rl1_line([1.5, 2.5, 3.5, 9.0, 4.5], (1.2, 2.1, 0.6), (1.0, 2.1, 0.6), 11.0),
    ]
    log = read_carmen(write_log(tmp_path / "rl.log", lines))
    np.testing.assert_allclose(log.poses, [[1.0, 2.0, 0.5], [1.2, 2.1, 0.6]])
    assert (log.angle_min, log.angle_increment) == (-1.0, 0.5)
    # 8.0 and 9.0 are at/above the message's own max_range (8.0): no return.
    np.testing.assert_array_equal(log.ranges >= log.range_max, [[0, 0, 1, 0, 0], [0, 0, 0, 1, 0]])


def test_non_increasing_timestamps_fall_back_to_step_index(tmp_path):
    lines = [flaser_line([1.0, 2.0], (i, 0, 0), 5.0 if i < 2 else 4.0 + i) for i in range(4)]
    log = read_carmen(write_log(tmp_path / "t.log", lines))
    assert log.time_source == "step_index"
    np.testing.assert_array_equal(log.t, [0, 1, 2, 3])


@pytest.mark.parametrize(
    ("bad", "words"),
    [
        ("FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0", "need 14 fields"),
        ("FLASER 3 1.0 abc 3.0 0 0 0 0 0 0 1.0 host 1.0", "'abc' is not a number"),
        ("FLASER 2 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0", "beam count must not change"),
        ("FLASER 3 1.0 2.0 3.0 nan 0 0 0 0 0 1.0 host 1.0", "pose (nan, 0, 0) is not finite"),
        ("FLASER 3 1.0 2.0 3.0 0 inf 0 0 0 0 1.0 host 1.0", "pose (0, inf, 0) is not finite"),
        ("FLASER 3 1.0 -2.0 3.0 0 0 0 0 0 0 1.0 host 1.0", "negative range"),
        ("FLASER x 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0", "not an integer"),
        ("1.0 2.0 3.0", "not a CARMEN message name"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path, bad, words):
    good = flaser_line([1.0, 2.0, 3.0], (0, 0, 0), 1.0)
    path = write_log(tmp_path / "bad.log", ["# header", good, "ODOM 0 0 0 0 0 0 1 h 1", bad, good])
    with pytest.raises(InputError) as info:
        read_carmen(path)
    (problem,) = info.value.problems
    assert problem.row == 4 and problem.file == str(path)
    assert words in problem.message and "--skip-bad-lines" in problem.fix
    assert str(path) in str(info.value) and "line 4" in str(info.value)

    log = read_carmen(path, skip_bad_lines=True)
    assert log.n_scans == 2 and len(log.skipped) == 1 and log.skipped[0].row == 4


def test_unknown_message_types_are_counted_not_fatal(tmp_path):
    lines = [flaser_line([1.0, 2.0], (0, 0, 0), 1.0), "FLASR 2 1 2", "NEFF 12.5", "MYMSG 1 2 3"]
    log = read_carmen(write_log(tmp_path / "u.log", lines))
    assert log.message_counts == {"FLASER": 1, "FLASR": 1, "MYMSG": 1, "NEFF": 1}
    assert log.unknown_messages == ["FLASR", "MYMSG"]


def test_every_bad_line_is_listed(tmp_path):
    good = flaser_line([1.0, 2.0], (0, 0, 0), 1.0)
    path = write_log(tmp_path / "bad.log", [good, "FLASER 2 1", good, "FLASER 2 1 2 3", good])
    with pytest.raises(InputError) as info:
        read_carmen(path)
    assert [p.row for p in info.value.problems] == [2, 4]


def test_empty_and_missing_logs(tmp_path):
    path = write_log(tmp_path / "empty.log.gz", ["# nothing", "ODOM 0 0 0 0 0 0 1 h 1"])
    with pytest.raises(InputError, match="no laser scans") as info:
        read_carmen(path)
    assert "ODOM" in str(info.value)
    with pytest.raises(InputError, match="not found"):
        read_carmen(tmp_path / "nope.log")


def test_gzip_detected_by_content_and_corrupt_gzip_reported(tmp_path):
    line = flaser_line([1.0, 2.0], (0, 0, 0), 1.0)
    plain_named_gz = write_log(tmp_path / "plain.log", [line]).rename(tmp_path / "plain.log.gz")
    assert read_carmen(plain_named_gz).n_scans == 1
    corrupt = tmp_path / "corrupt.log.gz"
    corrupt.write_bytes(gzip.compress((line + "\n").encode() * 50)[:60])
    with pytest.raises(InputError, match="cannot read"):
        read_carmen(corrupt)


# The README's table (scans x beams) and the FLASER conventions for each beam count.
REAL_LOGS = {
    "intel-corrected.log.gz": (910, 180, 1.0),
    "aces-corrected.log.gz": (440, 180, 1.0),
    "csail-corrected.log.gz": (406, 361, 0.5),
    "freiburg-079-corrected.log.gz": (4791, 360, 0.5),
    "fhw-corrected.log.gz": (488, 180, 1.0),
}


@pytest.mark.realdata
@pytest.mark.parametrize("name", sorted(REAL_LOGS))
def test_real_logs_match_readme(name):
    carmen_dir = require_carmen_dir()
    scans, beams, inc_deg = REAL_LOGS[name]
    log = read_carmen(carmen_dir / name)
    assert (log.n_scans, log.n_beams) == (scans, beams)
    assert math.degrees(log.angle_increment) == pytest.approx(inc_deg)
    assert log.message_counts["FLASER"] == scans and not log.skipped
    assert np.isfinite(log.poses).all() and np.isfinite(log.t).all()
    assert (np.diff(log.line_numbers) > 0).all()
    assert ((log.ranges > 0) & (log.ranges <= log.range_max)).all()
    # Every log has no-return readings (81.83 / 81.91 / 50.0) and they are all exactly range_max.
    assert 0 < log.no_return_count == int((log.ranges == np.float32(log.range_max)).sum())
    assert log.unknown_messages == []
    # README: csail's timestamps are unusable; intel's step back 4 times (by up to 0.11 s).
    assert log.time_source == ("step_index" if name.startswith(("csail", "intel")) else "log")


def test_many_bad_lines_are_counted_but_listed_only_up_to_a_cap(tmp_path):
    good = flaser_line([1.0, 2.0], (0, 0, 0), 1.0)
    path = write_log(tmp_path / "bad.log", [good] + ["FLASER 2 1"] * 300)
    with pytest.raises(InputError, match="300 bad lines") as info:
        read_carmen(path)
    assert len(info.value.problems) == MAX_LISTED
    log = read_carmen(path, skip_bad_lines=True)
    assert log.skipped_lines == 300 and len(log.skipped) == MAX_LISTED and log.n_scans == 1


@pytest.mark.parametrize(
    ("bad", "quoted"),
    [
        ("\x1b[31mRED\x1b[0m 1 2", "'\\x1b[31mRED\\x1b[0m' is not a CARMEN message name"),
        ("FLASER \x1b]0;title\x07 1 2", "beam count '\\x1b]0;title\\x07' is not an integer"),
        ("FLASER 3 1.0 \x1b[2J 3.0 0 0 0 0 0 0 1.0 host 1.0", "range: '\\x1b[2J' is not a number"),
        ("G" * 10_000_000, "... (10000000 characters)' is not a CARMEN message name"),
        ("FLASER " + "9" * 100 + "x", "... (101 characters)' is not an integer"),
    ],
    ids=["escape-name", "escape-count", "escape-range", "10MB-token", "long-count"],
)
def test_bad_input_is_quoted_short_and_escaped(tmp_path, bad, quoted):
    """Escape bytes of a log never reach the terminal and a 10 MB garbage line is not echoed whole."""
    good = flaser_line([1.0, 2.0, 3.0], (0, 0, 0), 1.0)
    path = write_log(tmp_path / "bad.log", [good, bad])
    with pytest.raises(InputError) as info:
        read_carmen(path)
    text = str(info.value)
    assert quoted in text and "line 2" in text
    assert "\x1b" not in text and "\x07" not in text and len(text) < 600
