"""What the runtime's public API accepts, checked in one place (docs/runtime.md, "Inputs").

`Localizer` and `AdaptiveMCL.init_pose` call these before anything reaches the filter or the describer,
so a bad value is refused with a `RuntimeInputError` naming the argument, what was expected and what was
given, instead of surfacing later as a NaN pose, an IndexError or an onnxruntime failure. The checks are
O(values) numpy, no Python loop over beams or pixels: an update pays microseconds for them.
"""

from __future__ import annotations

import math
import os

import numpy as np

from pipeline.errors import RuntimeInputError, excerpt

#: |x|, |y| (m) and |theta| (rad) of an odometry reading: UTM coordinates fit; squares stay far from overflow.
ODOMETRY_LIMIT = 1e7
#: |dx|, |dy| (m) between consecutive odometry readings: far above any robot's step, below a glitch's.
STEP_LIMIT_M = 1e3
IMAGE_LAYOUTS = "(H, W, 3) uint8 RGB or (3, H, W) float in [0, 1]"
_AXES = ("x", "y", "theta")


def _real(value, name: str, expected: str) -> np.ndarray:
    """`value` as a float64 array, refused unless it is integers or floats (not bool, complex, text, objects)."""
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):  # ragged nesting
        raise RuntimeInputError(f"{name}: expected {expected}, got a ragged {type(value).__name__}") from None
    if a.dtype.kind not in "iuf":
        raise RuntimeInputError(f"{name}: expected {expected}, got dtype {a.dtype} ({excerpt(value)})")
    return a.astype(np.float64, copy=False)


def _pose3(value, name: str) -> np.ndarray:
    """Three finite values x, y (m), theta (rad)."""
    expected = "3 finite values x, y (m), theta (rad)"
    p = _real(value, name, expected)
    if p.shape != (3,):
        raise RuntimeInputError(f"{name}: expected {expected}, got shape {p.shape}")
    finite = np.isfinite(p)
    if not finite.all():
        i = int(np.argmin(finite))
        raise RuntimeInputError(f"{name}: expected {expected}, got {excerpt(p.tolist())} ({_AXES[i]} is {p[i]})")
    return p


def odometry(value, previous: np.ndarray | None = None) -> np.ndarray:
    """The odometry reading (x, y, theta in the odometry frame) as (3,) float64; `previous`: the last one
    accepted since the filter started, for the step bound."""
    o = _pose3(value, "odometry")
    big = np.abs(o) > ODOMETRY_LIMIT
    if big.any():
        i = int(np.argmax(big))
        raise RuntimeInputError(f"odometry: expected |x|, |y| (m) and |theta| (rad) up to {ODOMETRY_LIMIT:g}, got "
                                f"{_AXES[i]} = {o[i]:g}")
    if previous is not None:
        step = float(max(abs(o[0] - previous[0]), abs(o[1] - previous[1])))
        if step > STEP_LIMIT_M:
            raise RuntimeInputError(
                f"odometry: expected a step of at most {STEP_LIMIT_M:g} m in x and y from the previous reading "
                f"({previous[0]:g}, {previous[1]:g}), got ({o[0]:g}, {o[1]:g}): a glitch, or the odometry frame "
                f"was reset (then call reset())")
    return o


def ranges(value, beams: int | None, angle_increment: float, *, name: str = "scan",
           beams_from: str = "the bundle's laser") -> np.ndarray:
    """A scan's ranges (m) as (B,) float64: 1-D, `beams` of them (`beams_from` says whose count; None: any
    count a laser can have at `angle_increment`), none negative. +inf (no return), NaN (invalid) and -inf
    (too close, REP 117) stay: the sensor models skip them or read them as max-range readings (sensor.py),
    as they do readings >= range_max."""
    r = _real(value, name, "ranges in metres")
    if r.ndim != 1:
        raise RuntimeInputError(f"{name}: expected a 1-D array of ranges (m), one per beam, got shape {r.shape}")
    if beams is not None and len(r) != beams:
        raise RuntimeInputError(f"{name}: expected {beams} ranges ({beams_from}), got {len(r)}")
    most = math.floor(2.0 * math.pi / abs(angle_increment) + 1e-9) + 1 if angle_increment else 1
    if beams is None and not 1 <= len(r) <= most:
        raise RuntimeInputError(f"{name}: expected 1 to {most} ranges (a full turn at the laser's "
                                f"{math.degrees(angle_increment):g} deg increment), got {len(r)}")
    below = r < 0
    if below.any():
        neg = np.flatnonzero(below & (r != -np.inf))
        if neg.size:
            i = int(neg[0])
            raise RuntimeInputError(f"{name}: expected ranges >= 0 m (+inf: no return, NaN: invalid reading), got "
                                    f"{r[i]:g} at beam {i} ({neg.size} negative)")
    return r


def scan_geometry(scan) -> None:
    """A `Scan` handed in whole: its ranges as `ranges` checks them (any count its own geometry allows)."""
    geometry = np.array([scan.angle_min, scan.angle_increment, scan.range_max], dtype=np.float64)
    if not np.isfinite(geometry).all() or scan.range_max <= 0 or scan.angle_increment == 0:
        raise RuntimeInputError(f"scan: expected finite angle_min, a non-zero angle_increment and range_max > 0, "
                                f"got {excerpt(geometry.tolist())}")
    ranges(scan.ranges, None, scan.angle_increment)


def image(value):
    """A camera image, returned as given. A path (decoded by the describer) passes; an array must be
    IMAGE_LAYOUTS (what the describer reads), float values finite and in [0, 1]."""
    if value is None or isinstance(value, str | os.PathLike):
        return value
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):
        raise RuntimeInputError(f"image: expected {IMAGE_LAYOUTS} or a file path, got a ragged "
                                f"{type(value).__name__}") from None
    given = f"shape {a.shape} {a.dtype}"
    if a.size == 0:
        raise RuntimeInputError(f"image: expected {IMAGE_LAYOUTS}, got an empty array ({given})")
    if a.dtype == np.uint8:
        if a.ndim != 3 or a.shape[-1] != 3:
            hint = ": channel-first, transpose it to (H, W, 3)" if a.ndim == 3 and a.shape[0] == 3 else ""
            raise RuntimeInputError(f"image: expected {IMAGE_LAYOUTS}, got {given}{hint}")
        return value
    if a.dtype.kind != "f":
        raise RuntimeInputError(f"image: expected {IMAGE_LAYOUTS}, got {given}")
    if a.ndim != 3 or a.shape[0] != 3:
        hint = ": channel-last float, give it as (3, H, W) or as uint8" if a.ndim == 3 and a.shape[-1] == 3 else ""
        raise RuntimeInputError(f"image: expected {IMAGE_LAYOUTS}, got {given}{hint}")
    lo, hi = float(a.min()), float(a.max())  # NaN propagates: one pass each, no isfinite mask unless needed
    if not (math.isfinite(lo) and math.isfinite(hi)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise RuntimeInputError(f"image: expected finite values in [0, 1], got {a[tuple(bad)]} at "
                                f"{tuple(int(i) for i in bad)} ({given})")
    if lo < 0.0 or hi > 1.0:
        raise RuntimeInputError(f"image: expected float values in [0, 1], got {lo:g}..{hi:g} ({given}): divide "
                                f"an 8-bit image by 255, or give it as uint8 (H, W, 3)")
    return value


def pose(value, lmap, *, name: str = "init_pose") -> np.ndarray:
    """A pose the filter is told it is at, as (3,) float64: finite, on the map, in neither an occupied cell
    nor unknown space (a trusted pose there would be reported as tracking where no robot can be)."""
    p = _pose3(value, name)
    where = f"({p[0]:g}, {p[1]:g})"
    cell = lmap.cell_of(p[0], p[1])
    if cell is None:
        x0, y0, size = lmap.origin_x, lmap.origin_y, lmap.resolution
        raise RuntimeInputError(f"{name}: expected a position on the map (x {x0:g}..{x0 + lmap.width * size:g} m, "
                                f"y {y0:g}..{y0 + lmap.height * size:g} m), got {where}")
    if lmap.occupied[cell]:
        raise RuntimeInputError(f"{name}: expected a position in the map's free space, got {where}: an occupied cell")
    if not lmap.known(p[0], p[1]):
        raise RuntimeInputError(f"{name}: expected a position in the map's free space, got {where}: unknown space")
    return p
