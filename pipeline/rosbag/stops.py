"""Capture stops in a recorded drive: which camera frames make up each 6-view stop.

`turning_stops` finds the paper's capture: the robot stands (its base within `radius` of where it
stopped) and turns through the rig's headings; view k is the frame nearest to the first frame's
heading + rig offset k. `stops_every` is the weaker capture from continuous driving: a stop every
`spacing` metres of travel, view k the frame within `spacing / 2` whose heading is nearest to the
stop's heading + offset k, so views differ in position and the headings only come as the drive gave
them. Turns and places without a frame for every view are returned as `incomplete`, never dropped unsaid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.runtime.motion import wrap_angle


@dataclass
class Stop:
    frames: list[int]  # frame index per rig view
    heading_error: float  # worst |heading - (stop heading + offset)|, radians
    spread: float  # largest distance of a view's camera from their mean, m


@dataclass
class Incomplete:
    at: tuple[float, float]
    stamp: float
    missing_views: list[int]
    why: str


def _pick(candidates: np.ndarray, headings: np.ndarray, h0: float, offsets: np.ndarray):
    """For each offset the candidate frame nearest to h0 + offset and its heading error."""
    err = np.abs(wrap_angle(headings[candidates][None, :] - (h0 + offsets)[:, None]))
    best = np.argmin(err, axis=1)
    return candidates[best], err[np.arange(len(offsets)), best]


def _stop(frames: np.ndarray, err: np.ndarray, cam: np.ndarray) -> Stop:
    xy = cam[frames, :2]
    return Stop([int(f) for f in frames], float(err.max()), float(np.max(np.hypot(*(xy - xy.mean(axis=0)).T))))


def turning_stops(stamps: np.ndarray, base_xy: np.ndarray, cam: np.ndarray, offsets, *, radius: float,
                  tolerance: float) -> tuple[list[Stop], list[Incomplete]]:
    """Stops where the robot turned in place (see module docstring); frames in time order."""
    offsets = np.asarray(offsets, dtype=np.float64)
    stops, incomplete = [], []
    n, start = len(stamps), 0
    while start < n:
        end = start + 1
        while end < n and math.hypot(*(base_xy[end] - base_xy[start])) <= radius:
            end += 1
        idx = np.arange(start, end)
        start = end
        if len(idx) < 2:
            continue
        turned = np.unwrap(cam[idx, 2])
        span = float(turned.max() - turned.min())
        needed = float(np.ptp(offsets)) - tolerance
        frames, err = _pick(idx, cam[:, 2], cam[idx[0], 2], offsets)
        missing = [k for k in range(len(offsets)) if err[k] > tolerance]
        at = (float(base_xy[idx[0], 0]), float(base_xy[idx[0], 1]))
        if span < needed:
            if span >= math.pi / 2:
                incomplete.append(Incomplete(at, float(stamps[idx[0]]), missing,
                                             f"turned {math.degrees(span):.0f} deg in place, a stop needs "
                                             f"{math.degrees(needed):.0f}"))
            continue
        if missing:
            incomplete.append(Incomplete(at, float(stamps[idx[0]]), missing,
                                         f"no frame within {math.degrees(tolerance):.1f} deg of these views"))
            continue
        stops.append(_stop(frames, err, cam))
    return stops, incomplete


def stops_every(stamps: np.ndarray, base_xy: np.ndarray, cam: np.ndarray, offsets, *, spacing: float,
                tolerance: float) -> tuple[list[Stop], list[Incomplete]]:
    """A stop every `spacing` metres of travel (see module docstring)."""
    offsets = np.asarray(offsets, dtype=np.float64)
    if len(stamps) == 0:
        return [], []
    travelled = np.r_[0.0, np.cumsum(np.hypot(*np.diff(base_xy, axis=0).T))]
    stops, incomplete = [], []
    for d in np.arange(0.0, travelled[-1] + 1e-9, spacing):
        centre = int(np.argmin(np.abs(travelled - d)))
        near = np.nonzero(np.hypot(*(base_xy - base_xy[centre]).T) <= spacing / 2)[0]
        frames, err = _pick(near, cam[:, 2], cam[centre, 2], offsets)
        missing = [k for k in range(len(offsets)) if err[k] > tolerance]
        if missing:
            incomplete.append(Incomplete((float(base_xy[centre, 0]), float(base_xy[centre, 1])),
                                         float(stamps[centre]), missing,
                                         f"no frame within {spacing / 2:.1f} m looks within "
                                         f"{math.degrees(tolerance):.0f} deg of these views"))
            continue
        if len(set(frames.tolist())) < len(frames):
            incomplete.append(Incomplete((float(base_xy[centre, 0]), float(base_xy[centre, 1])),
                                         float(stamps[centre]), [], "one frame would serve two views"))
            continue
        stops.append(_stop(frames, err, cam))
    return stops, incomplete
