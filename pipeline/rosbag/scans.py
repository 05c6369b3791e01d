"""LaserScan messages as real lasers publish them, brought to one counter-clockwise beam grid.

A recording's first scan fixes the grid (angle_min, angle_increment, beams). Every scan is read as
REP 117 says and real drivers bend it: a negative `angle_increment` (a clockwise sweep) is reversed;
readings of 0, below the message's `range_min`, -inf or NaN are invalid (NaN: the sensor models skip them,
as nav2's AMCL skips readings at or below range_min); readings beyond `range_max` are no return
(+inf). A laser whose beam count changes by a few from scan to scan (an RPLidar's does: its motor
speed sets the count) is resampled onto the first scan's grid, each grid beam taking the reading
nearest in angle within half an increment. A laser mounted upside down (its z axis pointing down)
sees the floor mirrored: `mirror` turns such scans into those of an upright laser at the same yaw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Beam counts may differ from the first scan's by this many (or 1 % of them) and still be resampled.
COUNT_SLACK = 2
COUNT_SLACK_SHARE = 0.01


@dataclass(frozen=True)
class Grid:
    """A counter-clockwise beam grid: beam k at angle_min + k * angle_increment (radians, increment > 0)."""

    angle_min: float
    angle_increment: float
    beams: int

    @property
    def angle_max(self) -> float:
        return self.angle_min + (self.beams - 1) * self.angle_increment

    def fits(self, other: Grid) -> bool:
        """Whether `other` covers the same sweep, give or take the beam counts of a spinning laser."""
        slack = max(COUNT_SLACK, math.ceil(COUNT_SLACK_SHARE * self.beams))
        return (abs(other.beams - self.beams) <= slack
                and abs(other.angle_min - self.angle_min) <= slack * self.angle_increment
                and abs(other.angle_max - self.angle_max) <= slack * self.angle_increment)


def counter_clockwise(ranges: np.ndarray, angle_min: float, angle_increment: float) -> tuple[np.ndarray, Grid]:
    """(ranges, grid) with a positive increment: a clockwise sweep's beams reversed."""
    n = len(ranges)
    if angle_increment < 0:
        return ranges[::-1], Grid(angle_min + (n - 1) * angle_increment, -angle_increment, n)
    return ranges, Grid(angle_min, angle_increment, n)


def cleaned(ranges: np.ndarray, range_min: float, range_max: float) -> np.ndarray:
    """float32 ranges: invalid readings (<= 0, below range_min, NaN, -inf) NaN; beyond range_max +inf."""
    r = np.asarray(ranges, dtype=np.float32).copy()
    with np.errstate(invalid="ignore"):
        r[~(r >= float(range_min)) | (r <= 0.0)] = np.nan  # NaN and -inf compare False: NaN
        r[r > range_max] = np.inf
    return r


def resample(ranges: np.ndarray, src: Grid, dst: Grid) -> np.ndarray:
    """`ranges` on grid `src` read on grid `dst`: each beam the reading nearest in angle, NaN where none
    lies within half of `dst`'s increment."""
    if src == dst:
        return ranges
    angles = dst.angle_min + dst.angle_increment * np.arange(dst.beams)
    k = np.rint((angles - src.angle_min) / src.angle_increment).astype(np.int64)
    inside = (k >= 0) & (k < src.beams)
    k = np.clip(k, 0, src.beams - 1)
    near = np.abs(src.angle_min + k * src.angle_increment - angles) <= 0.5 * dst.angle_increment + 1e-9
    return np.where(inside & near, ranges[k], np.float32(np.nan)).astype(np.float32)


def mirror(ranges: np.ndarray, grid: Grid) -> tuple[np.ndarray, Grid]:
    """Scans of an upside-down laser as an upright one at the same yaw sees them: beam angle a becomes -a.
    `ranges` may be (B,) or (N, B)."""
    return ranges[..., ::-1], Grid(-grid.angle_max, grid.angle_increment, grid.beams)
