"""Quality without ground truth: beam agreement against ray-cast scans and a brute-force twin, spread, states,
and `assess` on hand-built sequences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.runtime.grid import LaserMap
from pipeline.runtime.quality import QualityRule, assess, beam_agreement, spread_m, state_changes
from pipeline.runtime.sensor import subsample
from tests.fixtures.capture_site import cast_scan, floor_map

RANGE_MAX = 8.0
ANGLES = np.linspace(math.radians(-135), math.radians(135), 91)
A0, INC = float(ANGLES[0]), float(ANGLES[1] - ANGLES[0])
POSES = np.array([[1.0, 1.0, 0.0], [2.0, 3.0, 0.5], [4.0, 1.0, 1.5], [5.0, 3.0, -2.0], [1.5, 2.0, 2.8]])


@pytest.fixture(scope="module")
def site():
    occ = floor_map()
    return occ, LaserMap.from_occupancy(occ, max_distance=2.0)


def scans_at(occ, poses) -> np.ndarray:
    return np.stack([cast_scan(occ, x, y, th, ANGLES, RANGE_MAX) for x, y, th in poses])


def agreement(lmap, poses, ranges, **kw) -> np.ndarray:
    return beam_agreement(lmap, poses, ranges, A0, INC, RANGE_MAX, **{"tolerance_m": 0.1, **kw})


def brute_agreement(lmap, poses, ranges, mount=(0.0, 0.0, 0.0), tolerance_m=0.1, range_min=0.0,
                    beams=None) -> np.ndarray:
    """Twin: one beam at a time, the distance to the nearest occupied cell by a search over all of them."""
    occ_rows, occ_cols = np.nonzero(lmap.occupied)
    out = []
    for (x, y, th), scan in zip(poses, ranges, strict=True):
        lx = x + math.cos(th) * mount[0] - math.sin(th) * mount[1]
        ly = y + math.sin(th) * mount[0] + math.cos(th) * mount[1]
        lth = th + mount[2]
        used = agree = 0
        for k in (range(len(scan)) if beams is None else beams):
            r = float(scan[k])
            if not (math.isfinite(r) and r > 0 and r >= range_min and r < RANGE_MAX):
                continue
            used += 1
            a = A0 + INC * k
            col = math.floor((lx + r * math.cos(lth + a) - lmap.origin_x) / lmap.resolution)
            row = math.floor((ly + r * math.sin(lth + a) - lmap.origin_y) / lmap.resolution)
            d = lmap.max_distance
            if 0 <= row < lmap.height and 0 <= col < lmap.width:
                d = min(d, float(np.min(np.hypot(occ_rows - row, occ_cols - col))) * lmap.resolution)
            agree += d <= tolerance_m + 1e-6
        out.append(agree / used if used else math.nan)
    return np.array(out)


def test_scans_cast_at_the_true_pose_agree(site):
    occ, lmap = site
    got = agreement(lmap, POSES, scans_at(occ, POSES))
    assert got.shape == (len(POSES),)
    assert np.all(got >= 0.98), got


def test_shifted_or_rotated_estimates_disagree(site):
    occ, lmap = site
    ranges = scans_at(occ, POSES)
    true = agreement(lmap, POSES, ranges)
    shifted = POSES + [0.7, -0.7, 0.0]  # 1 m off, diagonally: no wall keeps its endpoints
    shifted[:, :2] = np.clip(shifted[:, :2], 0.3, [5.7, 3.7])
    turned = POSES + [0.0, 0.0, math.pi / 2]
    for wrong in (shifted, turned):
        got = agreement(lmap, wrong, ranges)
        assert np.all(got < 0.4), got
        assert np.all(true - got > 0.55)


def test_equals_a_brute_force_twin(site):
    occ, lmap = site
    rng = np.random.default_rng(3)
    n = 40
    poses = np.column_stack([rng.uniform(-1.0, 7.0, n), rng.uniform(-1.0, 5.0, n), rng.uniform(-np.pi, np.pi, n)])
    truth = np.column_stack([rng.uniform(0.3, 5.7, n), rng.uniform(0.3, 3.7, n), poses[:, 2]])
    ranges = scans_at(occ, truth)
    ranges[rng.random(ranges.shape) < 0.1] = np.nan
    ranges[rng.random(ranges.shape) < 0.05] = RANGE_MAX
    mount = (0.2, -0.1, 0.3)
    for kw in ({}, {"base_from_laser": mount, "tolerance_m": 0.05, "range_min": 0.5},
               {"tolerance_m": 0.3, "max_beams": 30}, {"base_from_laser": mount, "tolerance_m": 0.0}):
        got = agreement(lmap, poses, ranges, **kw)
        beams = subsample(len(ANGLES), kw["max_beams"]) if "max_beams" in kw else None
        want = brute_agreement(lmap, poses, ranges, mount=kw.get("base_from_laser", (0.0, 0.0, 0.0)),
                               tolerance_m=kw.get("tolerance_m", 0.1), range_min=kw.get("range_min", 0.0), beams=beams)
        np.testing.assert_array_equal(got, want)
    # on the true poses too, where most endpoints are on walls
    np.testing.assert_array_equal(agreement(lmap, truth, ranges), brute_agreement(lmap, truth, ranges))


def test_beams_without_an_endpoint_are_not_counted(site):
    occ, lmap = site
    ranges = scans_at(occ, POSES)
    assert np.all(agreement(lmap, POSES, ranges) == 1.0)
    bad = ranges.copy()
    # NaN, +-inf, 0, negative, below range_min, at or beyond range_max: each would land off a wall if counted
    bad[:, ::2] = np.resize(np.array([np.nan, np.inf, -np.inf, 0.0, -1.0, 0.2, RANGE_MAX, 9.0], np.float32),
                            bad[:, ::2].shape)
    assert np.all(agreement(lmap, POSES, bad, range_min=0.3) == 1.0)
    assert agreement(lmap, POSES, bad, range_min=0.1)[0] < 1.0  # 0.2 m readings now count, and miss
    bad[2] = np.nan
    got = agreement(lmap, POSES, bad, range_min=0.3)
    assert np.isnan(got[2]) and np.all(got[[0, 1, 3, 4]] == 1.0)
    poses = POSES.copy()
    poses[1, 0] = np.nan
    assert np.isnan(agreement(lmap, poses, ranges)[1])


def test_the_laser_mount_is_applied(site):
    occ, lmap = site
    mount = (0.3, 0.1, math.pi / 2)
    c, s = np.cos(POSES[:, 2]), np.sin(POSES[:, 2])
    laser = np.column_stack([POSES[:, 0] + c * mount[0] - s * mount[1], POSES[:, 1] + s * mount[0] + c * mount[1],
                             POSES[:, 2] + mount[2]])
    ranges = scans_at(occ, laser)
    assert np.all(agreement(lmap, POSES, ranges, base_from_laser=mount) >= 0.98)
    assert np.all(agreement(lmap, POSES, ranges) < 0.5)


def test_chunks_give_the_same_result(site):
    occ, lmap = site
    rng = np.random.default_rng(5)
    poses = np.repeat(POSES, 7, axis=0) + rng.normal(0.0, [0.3, 0.3, 0.2], (7 * len(POSES), 3))
    ranges = np.repeat(scans_at(occ, POSES), 7, axis=0)
    one = agreement(lmap, poses, ranges, chunk=len(poses))
    for chunk in (1, 4, 16):
        np.testing.assert_array_equal(agreement(lmap, poses, ranges, chunk=chunk), one)
    assert len(agreement(lmap, np.zeros((0, 3)), np.zeros((0, 91), np.float32))) == 0


def test_spread_is_the_std_along_the_longest_axis():
    rng = np.random.default_rng(0)
    cov = []
    for _ in range(20):
        m = rng.normal(size=(3, 3))
        cov.append(m @ m.T)
    cov = np.array(cov)
    want = np.sqrt(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1])
    np.testing.assert_allclose(spread_m(cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]), want, rtol=1e-12)
    assert spread_m(4.0, 0.0, 1.0) == 2.0
    assert spread_m(0.0, 0.0, 0.0) == 0.0


def test_state_changes():
    assert state_changes([]) == []
    assert state_changes(["relocalising", "relocalising", "tracking", "tracking", "lost", "relocalising",
                          "tracking"]) == [
        {"step": 0, "from": None, "to": "relocalising"}, {"step": 2, "from": "relocalising", "to": "tracking"},
        {"step": 4, "from": "tracking", "to": "lost"}, {"step": 5, "from": "lost", "to": "relocalising"},
        {"step": 6, "from": "relocalising", "to": "tracking"}]


RULE = QualityRule(agreement=0.6, spread_m=0.5, hold=3)


def sequence(spec: str):
    """One character a step: g good (tracking, agreeing, tight), w wide (agreeing, spread), b bad agreement
    while tracking, l lost (agreement good), r relocalising, n no usable beam (tracking, tight)."""
    agree = {"g": 0.9, "w": 0.9, "b": 0.2, "l": 0.9, "r": 0.1, "n": np.nan}
    spread = {"g": 0.1, "w": 2.0, "b": 0.1, "l": 0.1, "r": 5.0, "n": 0.1}
    state = {"g": "tracking", "w": "tracking", "b": "tracking", "l": "lost", "r": "relocalising", "n": "tracking"}
    return [agree[c] for c in spec], [spread[c] for c in spec], [state[c] for c in spec]


def test_assess_converged_and_held():
    a = assess(*sequence("rrrwggggbgggg"), RULE)  # one bad step is not losing track
    assert a["converged_step"] == 4 and a["lost_steps"] == [] and a["converged"] is True
    assert a["agreement_median"] == 0.9 and a["spread_median_m"] == 0.1
    np.testing.assert_array_equal(a["good_steps"], [c == "g" for c in "rrrwggggbgggg"])
    assert a["share_by_state"] == {"tracking": round(10 / 13, 4), "relocalising": round(3 / 13, 4), "lost": 0.0}
    assert a["state_changes"] == [{"step": 0, "from": None, "to": "relocalising"},
                                  {"step": 3, "from": "relocalising", "to": "tracking"}]


def test_assess_converged_then_lost_is_not_converged():
    a = assess(*sequence("rrgggggbbbbbb"), RULE)
    assert a["converged_step"] == 2 and a["lost_steps"] == [7] and a["converged"] is False
    # the filter's own verdict counts as bad even where the scan still agrees; back, then lost again
    a = assess(*sequence("gggglllgggggbbbrrr"), RULE)
    assert a["converged_step"] == 0 and a["lost_steps"] == [4, 12] and a["converged"] is False
    # a wide belief that still agrees is not losing track, nor is a step without beams
    a = assess(*sequence("ggggwwwwnnnngggg"), RULE)
    assert a["lost_steps"] == [] and a["converged"] is True
    assert math.isclose(a["agreement_median"], 0.9)


def test_assess_needs_the_whole_hold():
    # fewer than `hold` steps left decide nothing: not converged, not lost
    a = assess(*sequence("rrrrgg"), RULE)
    assert a["converged_step"] is None and a["converged"] is False and a["agreement_median"] is None
    a = assess(*sequence("ggggggbb"), RULE)
    assert a["lost_steps"] == [] and a["converged"] is True
    assert assess(*sequence("ggggggbbb"), RULE)["lost_steps"] == [6]
    assert assess([], [], [], RULE)["converged"] is False


def test_assess_kidnapping_search_is_not_lost():
    spec = "ggggggbbbbbrrggggg"
    kid = np.zeros(len(spec), bool)
    kid[6] = True
    a = assess(*sequence(spec), RULE, kidnapped=kid)
    assert a["converged_step"] == 0 and a["lost_steps"] == [] and a["converged"] is True
    assert assess(*sequence(spec), RULE)["lost_steps"] == [6]
    # never settling after the kidnapping is not "lost" either (metrics: recovery None), but a later loss is
    kid2 = np.zeros(len(spec), bool)
    kid2[[6, 12]] = True
    a = assess(*sequence("ggggggbbbbbbgggbbb"), RULE, kidnapped=kid2)
    assert a["lost_steps"] == [15]
    # nor is a bad stretch that a kidnapping cuts short
    kid3 = np.zeros(13, bool)
    kid3[8] = True
    assert assess(*sequence("ggggggbbbgggg"), RULE, kidnapped=kid3)["lost_steps"] == []
    assert assess(*sequence("ggggggbbbgggg"), RULE)["lost_steps"] == [6]


def test_defaults_agree():
    import dataclasses
    import inspect

    rule = QualityRule()
    assert inspect.signature(beam_agreement).parameters["tolerance_m"].default == rule.tolerance_m
    assert 0 < rule.agreement < 1 and rule.hold >= 1 and rule.spread_m > 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        rule.hold = 3


def test_assess_refuses_mismatched_lengths():
    with pytest.raises(ValueError, match="length"):
        assess([0.9, 0.9], [0.1], ["tracking", "tracking"], RULE)


def test_the_hold_counts_filter_updates_when_given_and_steps_map_back():
    """A 40 Hz laser repeats each update's evidence over many scans: with `updated`, 20 steps of a good
    stretch that hold only 4 updates do not converge; the verdict equals the one on the updates alone, with
    the run's step numbers."""
    rng = np.random.default_rng(3)
    n_up = 80
    per = rng.integers(1, 9, n_up)  # scans between updates, 1..8
    idx = np.r_[0, np.cumsum(per)[:-1]]
    n = int(per.sum())
    agreement_up = np.where((np.arange(n_up) >= 10) & ((np.arange(n_up) < 50) | (np.arange(n_up) >= 75)), 0.95, 0.3)
    states_up = ["relocalising"] * 10 + ["tracking"] * 70
    step_of = np.searchsorted(idx, np.arange(n), side="right") - 1  # each scan carries its last update's figures
    agreement, states = agreement_up[step_of], [states_up[k] for k in step_of]
    spread = np.full(n, 0.1)
    updated = np.zeros(n, bool)
    updated[idx] = True
    rule = QualityRule(hold=20)
    got = assess(agreement, spread, states, rule, updated=updated)
    twin = assess(agreement_up, np.full(n_up, 0.1), states_up, rule)  # the updates alone
    assert got["converged_step"] == idx[twin["converged_step"]] == idx[10]
    assert got["lost_steps"] == [int(idx[k]) for k in twin["lost_steps"]] == [int(idx[50])]
    assert got["converged"] is False and got["steps"] == n and got["updates"] == n_up
    assert np.array_equal(got["good_steps"], twin["good_steps"][step_of])
    by_steps = assess(agreement, spread, states, rule)  # without `updated`: 20 scans can be 3 updates
    assert by_steps["converged_step"] is not None and by_steps["converged_step"] <= got["converged_step"]
