"""CARMEN laser logs (`.log` or `.log.gz`): laser scans with the pose they were taken from.

Two laser messages are read; every other message type is counted and ignored:

* `FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts`. CARMEN writes the
  laser pose as `x y theta` and the robot pose as `odom_*`; `x y theta` is used (in the corrected logs
  of ../shared/data/carmen both are the SLAM-corrected pose and the front laser offset is 0). FLASER
  carries no beam geometry, so it follows the SICK LMS conventions: the scan starts at -90 deg
  (counter-clockwise), an odd beam count spans -90..+90 deg inclusive (increment pi/(n-1): 181, 361),
  an even one is 180 deg / n from -90 deg (180 -> 1 deg, 360 -> 0.5 deg).
* `ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode n r_1..r_n m
  rem_1..rem_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety side_safety
  turn_axis ipc_ts host logger_ts`: the geometry is in the message; the laser pose is used.

"No return" readings (a no-return code such as 81.83 / 81.91 / 50.0 within 0.005 m, a reading above
`range_max` or at/above a ROBOTLASER1's own max_range, zero, NaN or inf) are stored as exactly
`range_max` (float32). Downstream, **a range >= range_max means no return** (the RUNS contract).

A malformed line (wrong token count, a non-numeric or negative value, a beam geometry that differs
from the first scan's, a non-finite pose) is an `InputError` naming the file and 1-based line, with
every such line listed; `skip_bad_lines=True` skips and counts them instead.
"""

from __future__ import annotations

import gzip
import io
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import LaserLogConfig
from pipeline.errors import InputError, Problem, excerpt

#: Message types of CARMEN logs that carry nothing siteloc needs (RAWLASER* have no pose).
KNOWN_IGNORED = frozenset(
    "ODOM NEFF PARAM SYNC TRUEPOS RLASER LASER3 LASER4 RAWLASER1 RAWLASER2 RAWLASER3 RAWLASER4 "
    "ROBOTLASER2 GPSNMEA NMEAGGA NMEARMC SONAR BUMPER SCANMARK POSITIONLASER IMU VECTORMOVE "
    "ROBOTVELOCITY FOLLOWTRAJECTORY BASEVELOCITY".split()
)
LASER_MESSAGES = ("FLASER", "ROBOTLASER1")
_MESSAGE_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,39}$")  # CARMEN's names are short; a 10 MB token is garbage
_CODE_TOLERANCE = 0.005
_FIX_SKIP = "repair or delete the line, or pass --skip-bad-lines to skip malformed lines"
#: Malformed lines described one by one (all are counted): a wrong file must not print 100k lines.
MAX_LISTED = 100


@dataclass(frozen=True)
class CarmenLog:
    """The laser scans of one log, in file order. Angles are radians, distances metres."""

    path: Path
    t: np.ndarray  # (N,) float64 seconds: logger timestamps, or the step index (see time_source)
    time_source: str  # "log" or "step_index" (timestamps missing or not strictly increasing)
    poses: np.ndarray  # (N, 3) float64 map_from_base (x, y, theta): the corrected pose = ground truth
    ranges: np.ndarray  # (N, B) float32; >= range_max means no return
    angle_min: float
    angle_increment: float
    range_max: float
    line_numbers: np.ndarray  # (N,) int64, 1-based line of each scan in the file
    message_counts: dict[str, int]  # every message type seen (comments as "#"), sorted by name
    no_return_count: int  # readings turned into range_max
    skipped_lines: int = 0  # malformed lines skipped (skip_bad_lines)
    skipped: list[Problem] = field(default_factory=list)  # the first MAX_LISTED of them

    @property
    def unknown_messages(self) -> list[str]:
        """Message types that are neither laser messages nor known CARMEN ones (a typo shows up here)."""
        known = KNOWN_IGNORED | set(LASER_MESSAGES) | {"#"}
        return [kind for kind in self.message_counts if kind not in known]

    @property
    def n_scans(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def n_beams(self) -> int:
        return int(self.ranges.shape[1])

    @property
    def angles(self) -> np.ndarray:
        """Beam angles in the laser frame (radians, counter-clockwise, 0 = straight ahead)."""
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)


def flaser_geometry(n_beams: int) -> tuple[float, float]:
    """(angle_min, angle_increment) of an n-beam FLASER scan; see the module docstring."""
    if n_beams < 2:
        return -math.pi / 2, math.pi
    step = math.pi / (n_beams - 1) if n_beams % 2 else math.pi / n_beams
    return -math.pi / 2, step


class _BadLine(ValueError):
    """A malformed laser line; the message says what is wrong with it."""


@dataclass
class _Scan:
    line: int
    pose: tuple[float, float, float]
    t: float
    ranges: np.ndarray  # float64, raw readings
    angle_min: float
    angle_increment: float
    sensor_max: float  # the message's own maximum range (inf for FLASER)


def _floats(tokens: list[str], what: str) -> np.ndarray:
    try:
        values = np.array([float(tok) for tok in tokens], dtype=np.float64)
    except ValueError:
        bad = next(tok for tok in tokens if not _is_float(tok))
        raise _BadLine(f"{what}: '{excerpt(bad)}' is not a number") from None
    return values


def _is_float(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _count(tokens: list[str], index: int, what: str) -> int:
    if index >= len(tokens):
        raise _BadLine(f"line ends before the {what}")
    try:
        n = int(tokens[index])
    except ValueError:
        raise _BadLine(f"{what} '{excerpt(tokens[index])}' is not an integer") from None
    if n < 0:
        raise _BadLine(f"{what} {n} is negative")
    return n


def _parse_flaser(tokens: list[str], line: int) -> _Scan:
    n = _count(tokens, 1, "beam count")
    expected = n + 11
    if len(tokens) != expected:
        raise _BadLine(
            f"{n} beams need {expected} fields (FLASER n r_1..r_n x y theta odom_x odom_y "
            f"odom_theta ipc_ts host logger_ts), found {len(tokens)}"
        )
    ranges = _floats(tokens[2 : 2 + n], "range")
    pose = _floats(tokens[2 + n : 5 + n], "pose")
    t = _floats(tokens[-1:], "logger timestamp")[0]
    angle_min, inc = flaser_geometry(n)
    return _Scan(line, (pose[0], pose[1], pose[2]), t, ranges, angle_min, inc, math.inf)


def _parse_robotlaser1(tokens: list[str], line: int) -> _Scan:
    n = _count(tokens, 8, "beam count")
    m = _count(tokens, 9 + n, "remission count")
    expected = n + m + 24
    if len(tokens) != expected:
        raise _BadLine(f"{n} beams and {m} remissions need {expected} fields, found {len(tokens)}")
    head = _floats(tokens[2:7], "laser parameters")  # start_angle fov angular_res max_range accuracy
    ranges = _floats(tokens[9 : 9 + n], "range")
    pose = _floats(tokens[10 + n + m : 13 + n + m], "laser pose")
    t = _floats(tokens[-1:], "logger timestamp")[0]
    if not (np.isfinite(head[:4]).all() and head[2] > 0 and head[3] > 0):
        raise _BadLine("start_angle, fov, angular_res, max_range must be finite; angular_res, max_range > 0")
    return _Scan(line, (pose[0], pose[1], pose[2]), t, ranges, float(head[0]), float(head[2]), float(head[3]))


def _check(scan: _Scan, first: _Scan | None) -> None:
    if not all(math.isfinite(v) for v in scan.pose):
        raise _BadLine("pose ({:g}, {:g}, {:g}) is not finite".format(*scan.pose))
    if scan.ranges.size == 0:
        raise _BadLine("a scan with no beams")
    if (scan.ranges < 0).any():
        raise _BadLine(f"negative range {scan.ranges[scan.ranges < 0][0]:g}")
    if first is None:
        return
    if scan.ranges.size != first.ranges.size:
        raise _BadLine(
            f"{scan.ranges.size} beams, but the first scan (line {first.line}) has {first.ranges.size}; "
            "the beam count must not change within a log"
        )
    if abs(scan.angle_min - first.angle_min) > 1e-6 or abs(scan.angle_increment - first.angle_increment) > 1e-9:
        raise _BadLine(f"beam angles differ from the first scan's (line {first.line})")


def _open_text(path: Path) -> io.TextIOBase:
    """Gzip is recognised by its magic bytes, not the suffix, so a mislabelled file still reads."""
    with open(path, "rb") as fh:
        magic = fh.read(2)
    if magic == b"\x1f\x8b":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def _no_return_mask(ranges: np.ndarray, sensor_max: np.ndarray, cfg: LaserLogConfig) -> np.ndarray:
    mask = ~np.isfinite(ranges) | (ranges <= 0) | (ranges > cfg.range_max) | (ranges >= sensor_max[:, None])
    for code in cfg.no_return_ranges:
        mask |= np.abs(ranges - code) <= _CODE_TOLERANCE
    return mask


def read_carmen(path: Path, cfg: LaserLogConfig | None = None, *, skip_bad_lines: bool = False) -> CarmenLog:
    """Read the laser scans of a CARMEN log; raise `InputError` listing every malformed line."""
    cfg = cfg or LaserLogConfig()
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"{path}: CARMEN log not found",
            [Problem(str(path), "file is missing", fix="give the path of a .log or .log.gz CARMEN file")],
        )
    counts: Counter[str] = Counter()
    scans: list[_Scan] = []
    problems: list[Problem] = []
    n_bad = 0
    first: _Scan | None = None

    def bad(lineno: int, message: str) -> None:
        nonlocal n_bad
        n_bad += 1
        if len(problems) < MAX_LISTED:
            problems.append(Problem(str(path), message, row=lineno, fix=_FIX_SKIP))

    try:
        with _open_text(path) as fh:
            for lineno, raw in enumerate(fh, start=1):
                tokens = raw.split()
                if not tokens:
                    continue
                kind = "#" if tokens[0].startswith("#") else tokens[0]
                if kind not in LASER_MESSAGES:
                    if kind != "#" and not _MESSAGE_NAME.match(kind):
                        bad(lineno, f"'{excerpt(kind)}' is not a CARMEN message name")
                        continue
                    counts[kind] += 1
                    continue
                try:
                    scan = (_parse_flaser if kind == "FLASER" else _parse_robotlaser1)(tokens, lineno)
                    _check(scan, first)
                except _BadLine as exc:
                    bad(lineno, f"{kind}: {exc}")
                    continue
                counts[kind] += 1
                first = first or scan
                scans.append(scan)
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise InputError(
            f"{path}: cannot read the log",
            [
                Problem(
                    str(path),
                    f"unreadable ({exc})",
                    fix="re-download or re-compress the file (gzip -t checks it)",
                )
            ],
        ) from None
    if n_bad and not skip_bad_lines:
        summary = f"{path}: malformed CARMEN log"
        if n_bad > len(problems):
            summary += f", {n_bad} bad lines, the first {len(problems)} listed"
        raise InputError(summary, problems)
    if not scans:
        raise InputError(
            f"{path}: no laser scans",
            [
                Problem(
                    str(path),
                    f"no FLASER or ROBOTLASER1 line (seen: {dict(sorted(counts.items())) or 'none'})",
                    fix="give a CARMEN log recorded with a laser",
                )
            ],
        )
    return _assemble(path, scans, counts, n_bad, problems, cfg)


def _assemble(
    path: Path, scans: list[_Scan], counts: Counter, n_bad: int, skipped: list[Problem], cfg: LaserLogConfig
) -> CarmenLog:
    ranges = np.stack([s.ranges for s in scans])
    sensor_max = np.array([s.sensor_max for s in scans])
    no_return = _no_return_mask(ranges, sensor_max, cfg)
    ranges = np.where(no_return, cfg.range_max, ranges).astype(np.float32)
    t = np.array([s.t for s in scans], dtype=np.float64)
    time_source = "log"
    if len(t) > 1 and not (np.isfinite(t).all() and (np.diff(t) > 0).all()):
        # csail's timestamps are rounded to 1e4 s, intel's step back 4 times by up to 0.1 s: such clocks
        # cannot give velocities, so time becomes the step index (recorded in time_source).
        t, time_source = np.arange(len(scans), dtype=np.float64), "step_index"
    return CarmenLog(
        path=path,
        t=t,
        time_source=time_source,
        poses=np.array([s.pose for s in scans], dtype=np.float64),
        ranges=ranges,
        angle_min=scans[0].angle_min,
        angle_increment=scans[0].angle_increment,
        range_max=float(cfg.range_max),
        line_numbers=np.array([s.line for s in scans], dtype=np.int64),
        message_counts=dict(sorted(counts.items())),
        no_return_count=int(no_return.sum()),
        skipped_lines=n_bad,
        skipped=list(skipped),
    )
