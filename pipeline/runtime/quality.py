"""Localization quality without ground truth: what a robot can tell about its own estimate.

A recording without a reference pose still says how well the estimate fits: the share of the scan's beams
whose endpoints, seen from the estimate, land within `tolerance_m` of a wall of the map; the particle spread;
the filter's state and when it changed. `assess` turns them into the figures `evaluation.metrics` reports
with ground truth: "converged at s" when the rule holds (agreement, spread and the tracking state) on the
`hold` steps from s, and "lost at s" after convergence, outside kidnapped intervals, when the scan disagrees
(or the filter says lost) on the `hold` steps from s. A replay that converged and then lost track is not
converged, as there. Unlike there, a stretch cut short by the run's end or a kidnapping decides nothing:
the share dips for a few steps (a passing crowd, a cluttered corner) where an error in metres does not.
The share reads "the map explains this much of the scan", so it cannot tell a wrong pose that looks the same
(a twin corridor) from the right one, and unmapped obstacles lower it at the right pose. numpy only (no
torch, no plotting): the robot's runtime may call it.

The defaults of `QualityRule` come from benchmarks/beam_agreement.py (five CARMEN logs and a synthetic campus
replayed from a uniform start with a kidnapping; which steps are right, which wrong, from ground truth): the
figures are in docs/results.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.runtime.grid import LaserMap
from pipeline.runtime.sensor import laser_poses, subsample

#: Filter states (`amcl.FilterState` values), in the order `share_by_state` lists them.
STATES = ("tracking", "relocalising", "lost")
#: Default endpoint tolerance, m (`QualityRule.tolerance_m`).
TOLERANCE_M = 0.15


def beam_agreement(lmap: LaserMap, poses: np.ndarray, ranges: np.ndarray, angle_min: float, angle_increment: float,
                   range_max: float, base_from_laser: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   tolerance_m: float = TOLERANCE_M, range_min: float = 0.0, max_beams: int | None = None,
                   chunk: int = 1024) -> np.ndarray:
    """(N,) share of each step's usable beams whose endpoint, seen from map_from_base `poses[n]` (x, y, theta),
    lies within `tolerance_m` of an occupied cell (the map's distance field, quantised to its cells).

    Usable: finite, positive (0 is an error code), >= range_min and < range_max (a beam with an endpoint), among
    the `max_beams` the filter's subsampling keeps (None: all). NaN where a step has no usable beam or its pose
    is not finite. Steps go through in chunks of `chunk` (`ranges` is only sliced: it may be rows read from disk
    a block at a time): memory stays at chunk x beams whatever the length."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if not hasattr(ranges, "shape"):  # an array, or rows read a block at a time (anything sliced into arrays)
        ranges = np.asarray(ranges)
    if len(ranges.shape) != 2 or len(ranges) != len(poses):
        raise ValueError(f"ranges must be (N, B) with N = {len(poses)} poses, got {ranges.shape}")
    idx = subsample(ranges.shape[1], max_beams) if max_beams else np.arange(ranges.shape[1])
    angles = angle_min + angle_increment * idx.astype(np.float64)
    # The distance field is float32 and quantised: a slack of a micrometre keeps "exactly at the tolerance" in.
    within = np.float64(tolerance_m) + 1e-6
    out = np.full(len(poses), np.nan)
    chunk = max(int(chunk), 1)
    for a in range(0, len(poses), chunk):
        lp = laser_poses(poses[a: a + chunk], tuple(base_from_laser))
        r = np.asarray(ranges[a: a + chunk])[:, idx].astype(np.float64)
        with np.errstate(invalid="ignore"):  # NaN compares False: not usable
            usable = (r > 0) & (r >= range_min) & (r < range_max) & np.isfinite(lp).all(axis=1)[:, None]
        r = np.where(usable, r, 0.0)  # no NaN or inf reaches the cell arithmetic
        th = np.where(np.isfinite(lp[:, 2]), lp[:, 2], 0.0)[:, None] + angles[None, :]
        x = np.where(np.isfinite(lp[:, 0]), lp[:, 0], 0.0)[:, None] + r * np.cos(th)
        y = np.where(np.isfinite(lp[:, 1]), lp[:, 1], 0.0)[:, None] + r * np.sin(th)
        agree = usable & (lmap.distance_at(x, y) <= within)
        n = usable.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[a: a + chunk] = np.where(n > 0, agree.sum(axis=1) / n, np.nan)
    return out


def spread_m(cov_xx, cov_xy, cov_yy) -> np.ndarray:
    """Particle spread, m: the square root of the largest eigenvalue of the xy covariance block (the std along
    the belief's longest axis); arrays of any one shape (from (N, 3, 3): cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1])."""
    a, b, c = (np.asarray(v, dtype=np.float64) for v in (cov_xx, cov_xy, cov_yy))
    top = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
    return np.sqrt(np.maximum(top, 0.0))


def state_changes(states) -> list[dict]:
    """[{"step": k, "from": a, "to": b}] for each change of state; step 0 as {"step": 0, "from": None, "to": s}."""
    states = [str(s) for s in states]
    if not states:
        return []
    out = [{"step": 0, "from": None, "to": states[0]}]
    out += [{"step": k, "from": states[k - 1], "to": states[k]} for k in range(1, len(states))
            if states[k] != states[k - 1]]
    return out


@dataclass(frozen=True)
class QualityRule:
    """When the estimate is taken to be right, without ground truth. The defaults come from
    benchmarks/beam_agreement.py (figures: docs/results.md): 0.8 of the beams within 0.15 m balances right steps
    called wrong against wrong ones called right on the CARMEN logs (per log the best threshold ranges from
    about 0.6 to 0.9: how much of a scan a map explains depends on the site); a hold of 20 steps, not metrics'
    10, because the share dips for a few steps where an error in metres does not; the spread barely separates
    (the filter reports its best cluster's, tight on a wrong pose too), so 0.5 m, the filter's converged_std_m,
    is a bound rather than a separator."""

    agreement: float = 0.8  # share of usable beams within `tolerance_m` of a wall, at least
    spread_m: float = 0.5  # particle spread (`spread_m`), at most
    hold: int = 20  # steps (filter updates, with `assess(updated=...)`) it must hold to converge, fail to lose
    tolerance_m: float = TOLERANCE_M  # for `beam_agreement`: 3 cells at 5 cm


def _holds(ok: np.ndarray, hold: int) -> np.ndarray:
    """Whether `ok` holds on all of steps i .. i + hold - 1, for every i (False where fewer remain)."""
    n = len(ok)
    idx = np.arange(n)
    # The first step >= i where ok fails (n if none): the run of True from i is that minus i.
    first_fail = np.minimum.accumulate(np.where(ok, n, idx)[::-1])[::-1]
    return ok & (first_fail - idx >= hold)


def _first(mask: np.ndarray, start: int, end: int) -> int | None:
    hits = np.flatnonzero(mask[start:end])
    return int(start + hits[0]) if len(hits) else None


def assess(agreement, spread, states, rule: QualityRule = QualityRule(), kidnapped=None, updated=None) -> dict:
    """`_assess` on the steps where the filter updated (`updated` (N,) bool; None: every step), the step numbers
    it reports those of the whole run. The hold then counts filter updates (one every update_min_d of travel),
    not scans: a 40 Hz laser would otherwise pass 20 steps in half a second, inside a room that looks like the
    right one; evidence comes with travel."""
    if updated is None:
        return _assess(agreement, spread, states, rule, kidnapped)
    states = [str(v) for v in states]
    n = len(states)
    idx = np.flatnonzero(np.asarray(updated, bool))
    if len(idx) == 0 or idx[0] != 0:
        idx = np.r_[0, idx]  # the first step stands for the start
    kid = None
    if kidnapped is not None:  # a kidnapping between updates marks the next update
        kid = np.zeros(len(idx), bool)
        at = np.searchsorted(idx, np.flatnonzero(np.asarray(kidnapped, bool)), side="left")
        kid[at[at < len(idx)]] = True
    out = _assess(np.asarray(agreement, np.float64)[idx], np.asarray(spread, np.float64)[idx],
                  [states[i] for i in idx], rule, kid)
    if out["converged_step"] is not None:
        out["converged_step"] = int(idx[out["converged_step"]])
    out["lost_steps"] = [int(idx[k]) for k in out["lost_steps"]]
    out["good_steps"] = out["good_steps"][np.searchsorted(idx, np.arange(n), side="right") - 1]
    out["steps"], out["updates"] = n, int(len(idx))
    out["state_changes"] = state_changes(states)
    names = list(STATES) + sorted(set(states) - set(STATES))
    arr = np.asarray(states)
    out["share_by_state"] = {s: round(float(np.mean(arr == s)), 4) if n else 0.0 for s in names}
    return out


def _assess(agreement, spread, states, rule: QualityRule = QualityRule(), kidnapped=None) -> dict:
    """Per-run quality figures from per-step agreement (`beam_agreement`), spread (`spread_m`) and states.

    `kidnapped` (N,) bool marks the steps where the robot was carried away (as the runs and estimates tables
    do): from each, the search until the rule holds again is neither converged nor lost (as in metrics)."""
    agreement = np.asarray(agreement, dtype=np.float64)
    spread = np.asarray(spread, dtype=np.float64)
    states = np.asarray([str(s) for s in states])
    n = len(agreement)
    if len(spread) != n or len(states) != n:
        raise ValueError(f"agreement, spread and states differ in length: {n}, {len(spread)}, {len(states)}")
    with np.errstate(invalid="ignore"):  # NaN agreement (no usable beam) is neither good nor bad
        good = (agreement >= rule.agreement) & (spread <= rule.spread_m) & (states == "tracking")
        bad = (agreement < rule.agreement) | (states == "lost")
    kid = sorted(int(k) for k in np.flatnonzero(np.asarray(kidnapped, bool)) if k > 0) if kidnapped is not None else []
    segment_end = np.full(n, n, dtype=np.int64)
    for k in reversed(kid):
        segment_end[:k] = k
    within = np.arange(n) + rule.hold <= segment_end  # a stretch from i ends before the next kidnapping
    settled = _holds(good, rule.hold) & within  # converged (or recovered) from i
    converged = _first(settled, 0, n)
    tracked = np.zeros(n, bool)
    if converged is not None:
        tracked[converged:] = True
    for k in kid:
        back = _first(settled, k, int(segment_end[k]))
        tracked[k: segment_end[k] if back is None else back] = False
    failing = _holds(tracked & bad, rule.hold) & within  # lost track from i
    lost: list[int] = []
    s = 0
    while converged is not None and s < n:
        at = _first(failing, s, n)
        if at is None:
            break
        lost.append(at)
        back = _first(settled, at, int(segment_end[at]))
        s = int(segment_end[at]) if back is None else back

    def median(a):
        a = a[np.isfinite(a)]
        return round(float(np.median(a)), 4) if len(a) else None

    names = list(STATES) + sorted(set(states.tolist()) - set(STATES))
    return {
        "steps": int(n),
        "converged_step": converged,
        "lost_steps": lost,
        "converged": converged is not None and not lost,
        "agreement_median": median(agreement[tracked]),
        "spread_median_m": median(spread[tracked]),
        "state_changes": state_changes(states.tolist()),
        "share_by_state": {s: round(float(np.mean(states == s)), 4) if n else 0.0 for s in names},
        "good_steps": good,
        "rule": {"agreement": rule.agreement, "spread_m": rule.spread_m, "hold": rule.hold,
                 "tolerance_m": rule.tolerance_m},
    }
