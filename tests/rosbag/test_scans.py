"""LaserScan normalisation (pipeline/rosbag/scans.py) against beam angles computed by hand."""

from __future__ import annotations

import math

import numpy as np

from pipeline.rosbag.scans import Grid, cleaned, counter_clockwise, mirror, resample


def _angles(g: Grid) -> np.ndarray:
    return g.angle_min + g.angle_increment * np.arange(g.beams)


def test_a_clockwise_sweep_reads_as_the_same_beams_counter_clockwise():
    n, a0, inc = 7, 1.2, -0.3  # beam k of the message points at 1.2 - 0.3 k
    r = np.arange(n, dtype=np.float32)
    out, g = counter_clockwise(r, a0, inc)
    assert g.angle_increment == 0.3 and math.isclose(g.angle_min, a0 + (n - 1) * inc)
    by_angle_in = dict(zip(np.round(a0 + inc * np.arange(n), 9), r, strict=True))
    by_angle_out = dict(zip(np.round(_angles(g), 9), out, strict=True))
    assert by_angle_in == by_angle_out
    same, g2 = counter_clockwise(r, -1.0, 0.3)
    assert same is r and g2 == Grid(-1.0, 0.3, n)


def test_invalid_readings_become_nan_and_far_ones_no_return():
    r = np.array([0.0, 0.05, 0.1, 2.0, np.nan, -np.inf, np.inf, 30.0, 12.0], dtype=np.float32)
    out = cleaned(r, range_min=0.1, range_max=12.0)
    assert np.isnan(out[[0, 1, 4, 5]]).all()  # 0, below range_min, NaN, -inf: invalid
    assert out[2] == np.float32(0.1) and out[3] == 2.0 and out[8] == 12.0  # at range_min and range_max: kept
    assert np.isposinf(out[[6, 7]]).all()  # +inf and beyond range_max: no return
    assert np.isnan(cleaned(np.array([0.0], np.float32), 0.0, 5.0)[0])  # 0 is never a reading
    assert r[0] == 0.0  # the input is not modified


def test_resample_takes_the_nearest_beam_within_half_an_increment():
    dst = Grid(-math.pi, 2 * math.pi / 360, 360)
    src = Grid(-math.pi, 2 * math.pi / 362, 362)  # an RPLidar turn with two beams more
    r = np.arange(362, dtype=np.float32)
    out = resample(r, src, dst)
    for j, a in enumerate(_angles(dst)):  # brute force: the reading taken is one of the nearest in angle
        gap = np.abs(_angles(src) - a)
        assert math.isclose(gap[int(out[j])], gap.min(), abs_tol=1e-12)
    short = Grid(-math.pi, src.angle_increment, 100)  # covers the first 100 beams only
    out = resample(np.ones(100, np.float32), short, dst)
    covered = _angles(dst) <= short.angle_max + 0.5 * dst.angle_increment
    assert np.isnan(out[~covered]).all() and (out[covered] == 1).all()
    assert dst.fits(src) and not dst.fits(Grid(-math.pi, src.angle_increment, 366))


def test_mirror_turns_beam_a_into_minus_a():
    g = Grid(-0.5, 0.25, 5)
    r = np.array([[1, 2, 3, 4, 5]], dtype=np.float32)
    out, m = mirror(r, g)
    assert math.isclose(m.angle_min, -g.angle_max) and m.angle_increment == g.angle_increment
    for k, a in enumerate(_angles(g)):  # the reading at a is now at -a
        j = int(np.argmin(np.abs(_angles(m) + a)))
        assert out[0, j] == r[0, k]
