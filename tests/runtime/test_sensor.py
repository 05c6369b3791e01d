"""Sensor models against closed forms, the compiled kernels against their numpy / brute-force twins."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from pipeline.config import SensorModelConfig
from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap
from pipeline.runtime import kernels
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.sensor import BeamModel, LikelihoodFieldModel, Scan, subsample


def cast_rays_brute(poses: np.ndarray, angles: np.ndarray, occupied: np.ndarray, resolution: float,
                    origin: tuple[float, float], range_max: float, step_cells: float = 0.01) -> np.ndarray:
    """Reference twin for tests: march every ray in tiny steps (slow, simple, independent)."""
    t = np.arange(0.0, range_max / resolution, step_cells)
    out = np.full((len(poses), len(angles)), float(range_max))
    h, w = occupied.shape
    for i, (x, y, th) in enumerate(np.asarray(poses, dtype=np.float64)):
        u0, v0 = (x - origin[0]) / resolution, (y - origin[1]) / resolution
        for b, a in enumerate(angles):
            col = np.floor(u0 + t * math.cos(th + a)).astype(np.int64)
            row = np.floor(v0 + t * math.sin(th + a)).astype(np.int64)
            outside = (row < 0) | (row >= h) | (col < 0) | (col >= w)
            stop = np.argmax(outside) if outside.any() else len(t)
            hits = np.nonzero(occupied[row[:stop], col[:stop]])[0]
            if len(hits):
                out[i, b] = t[hits[0]] * resolution
    return out


def box_map(w=6.0, h=4.0, res=0.05) -> OccupancyMap:
    """A closed rectangular room: walls one cell thick on the border, free inside."""
    grid = np.full((round(h / res), round(w / res)), FREE, dtype=np.int8)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = OCCUPIED
    return OccupancyMap(grid, res, -1.0, -2.0)


@pytest.fixture(scope="module")
def lmap():
    return LaserMap.from_occupancy(box_map(), 2.0)


def test_distance_field_and_free_sampling(lmap):
    # Distances are between cell centres: (0, 0) lies in column 20, the left wall is column 0.
    assert lmap.distance_at(0.0, 0.0) == pytest.approx(1.0, abs=1e-6)
    assert lmap.distance_at(4.93, 0.0) == pytest.approx(0.05, abs=1e-6)  # column 118, next to the wall (119)
    assert lmap.distance_at(-50.0, 0.0) == 2.0  # off the map: "far"
    poses = lmap.sample_free(5000, np.random.default_rng(0))
    assert lmap.is_free(poses[:, 0], poses[:, 1]).all()
    assert np.all((poses[:, 2] >= -math.pi) & (poses[:, 2] < math.pi))
    assert lmap.free_area_m2 == pytest.approx((6 - 0.1) * (4 - 0.1), rel=1e-6)


def test_subsample_keeps_ends_and_spreads_evenly():
    idx = subsample(1081, 60)
    assert idx[0] == 0 and idx[-1] == 1080 and len(idx) == 60
    assert np.ptp(np.diff(idx)) <= 1
    np.testing.assert_array_equal(subsample(30, 60), np.arange(30))


def test_likelihood_field_matches_the_closed_form(lmap):
    cfg = SensorModelConfig(max_beams=10, sigma_hit=0.2, z_hit=0.8, z_rand=0.2)
    model = LikelihoodFieldModel(lmap, cfg, range_max=10.0)
    # Robot at (0, 0) facing +x. A beam straight ahead reading 4.91 m ends in column 118, one cell (0.05 m)
    # from the right wall's column 119; a reading of 1.01 m at +90 degrees ends in row 60, 19 cells (0.95 m)
    # below the top wall's row 79 (the left wall is 20 cells away).
    scan = Scan(np.array([4.91, 1.01]), 0.0, math.pi / 2, 10.0)
    res = model.evaluate(np.array([[0.0, 0.0, 0.0]]), scan)

    def logp(d):
        return math.log(0.8 * math.exp(-0.5 * (d / 0.2) ** 2) / (math.sqrt(2 * math.pi) * 0.2) + 0.2 / 10.0)

    assert res.beams_used == 2
    assert res.log_likelihood[0] == pytest.approx(logp(0.05) + logp(0.95), abs=1e-5)
    assert res.relative_likelihood[0] == pytest.approx(math.exp((logp(0.05) + logp(0.95)) / 2 - logp(0.0)), rel=1e-5)


def test_invalid_readings_are_skipped_and_an_empty_scan_is_neutral(lmap):
    model = LikelihoodFieldModel(lmap, SensorModelConfig(), range_max=10.0)
    ok = Scan(np.array([4.91]), 0.0, 0.1, 10.0)
    messy = Scan(np.array([4.91, np.nan, np.inf, -np.inf, 0.01, 10.0, 25.0]), 0.0, 0.1, 10.0)
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 2.0]])
    np.testing.assert_allclose(model.evaluate(p, messy).log_likelihood, model.evaluate(p, ok).log_likelihood)
    empty = model.evaluate(p, Scan(np.full(5, np.nan), 0.0, 0.1, 10.0))
    assert empty.beams_used == 0 and np.all(empty.log_likelihood == 0)


def test_beam_skipping_leaves_out_what_the_map_lacks_and_only_that(lmap):
    cfg = SensorModelConfig(beam_skip=True)
    model = LikelihoodFieldModel(lmap, cfg, range_max=10.0)
    angles = np.linspace(-2.3, 2.3, 46)
    truth = np.array([[0.5, 0.0, 0.3]])
    ranges = kernels.cast_rays(truth, angles, lmap.occupied, kernels.safe_steps(lmap.occupied), lmap.resolution,
                               (lmap.origin_x, lmap.origin_y), 10.0)[0]
    rng = np.random.default_rng(0)
    tracked = truth + rng.normal(0.0, [0.05, 0.05, 0.02], (300, 3))
    scan = Scan(ranges, angles[0], angles[1] - angles[0], 10.0)
    # Nothing in front of the laser: no beam is skipped, the weights are evaluate's.
    plain, skipping = model.evaluate(tracked, scan), model.evaluate_skipping(tracked, scan)
    assert skipping.beams_used == plain.beams_used == 46
    np.testing.assert_allclose(skipping.log_likelihood, plain.log_likelihood, rtol=1e-6)
    # A person 0.6 m in front blocks beams 20-25: those, and only those, are left out of the weights.
    blocked = ranges.copy()
    blocked[20:26] = 0.6
    scan = Scan(blocked, angles[0], angles[1] - angles[0], 10.0)
    got = model.evaluate_skipping(tracked, scan)
    keep = np.ones(46, bool)
    keep[20:26] = False
    twin = model.evaluate(tracked, Scan(np.where(keep, blocked, np.nan), angles[0], angles[1] - angles[0], 10.0))
    assert got.beams_used == 40
    np.testing.assert_allclose(got.log_likelihood, twin.log_likelihood, rtol=1e-6)
    # ... while the kidnap rule's relative likelihood still scores every beam.
    np.testing.assert_allclose(got.relative_likelihood, model.evaluate(tracked, scan).relative_likelihood, rtol=1e-6)
    # A belief spread over the room agrees with few beams: rather than skip most, it uses them all.
    spread = lmap.sample_free(300, rng)
    assert model.evaluate_skipping(spread, scan).beams_used == 46
    np.testing.assert_allclose(model.evaluate_skipping(spread, scan).log_likelihood,
                               model.evaluate(spread, scan).log_likelihood, rtol=1e-6)
    with pytest.raises(ValueError, match="likelihood_field"):
        SensorModelConfig(beam_skip=True, model="beam")
    assert SensorModelConfig(model="beam").beam_skip  # the default does not stand in the beam model's way


def test_a_settled_belief_leaves_unmapped_obstacles_out_of_the_kidnap_likelihood_not_walls_seen_through(lmap):
    cfg = SensorModelConfig(beam_skip=False)
    model = LikelihoodFieldModel(lmap, cfg, range_max=10.0)
    angles = np.linspace(-2.3, 2.3, 46)
    truth = np.array([0.5, 0.0, 0.3])
    ranges = kernels.cast_rays(truth[None], angles, lmap.occupied, kernels.safe_steps(lmap.occupied),
                               lmap.resolution, (lmap.origin_x, lmap.origin_y), 10.0)[0]
    tracked = truth + np.random.default_rng(0).normal(0.0, [0.05, 0.05, 0.02], (300, 3))
    step = angles[1] - angles[0]
    # A car 0.6 m in front blocks beams 10-29 (20 of 46): short of the walls, seen from the belief.
    blocked = ranges.copy()
    blocked[10:30] = 0.6
    scan = Scan(blocked, angles[0], step, 10.0)
    unmapped, through_share = model.settled_view(truth, scan)
    assert np.array_equal(np.flatnonzero(unmapped), np.arange(10, 30)) and through_share == 0.0
    got, plain = model.evaluate(tracked, scan, settled=truth), model.evaluate(tracked, scan)
    # The weights still score every beam; the relative likelihood is the other 26 beams' (their twin).
    np.testing.assert_allclose(got.log_likelihood, plain.log_likelihood, rtol=1e-5)
    twin = model.evaluate(tracked, Scan(np.where(blocked == 0.6, np.nan, blocked), angles[0], step, 10.0))
    np.testing.assert_allclose(got.relative_likelihood, twin.relative_likelihood, rtol=1e-5)
    assert got.relative_likelihood.max() > 0.8 > plain.relative_likelihood.max()
    # Beams through a wall (a kidnapped robot seeing a room beyond) still count, and are counted: 20 of 46
    # pass the walls by 1.5 m, and 6 more return nothing where a wall lies in range.
    through = ranges.copy()
    through[10:30] = ranges[10:30] + 1.5
    through[40:46] = np.inf
    seen_through = model.evaluate(tracked, Scan(through, angles[0], step, 10.0), settled=truth)
    unmapped, through_share = model.settled_view(truth, Scan(through, angles[0], step, 10.0))
    assert not unmapped.any() and len(unmapped) == 40
    assert through_share == pytest.approx(26 / 46) and seen_through.through_share == pytest.approx(26 / 46)
    assert seen_through.relative_likelihood.max() < 0.8
    assert (got.beams_used, got.beams_judged, plain.beams_judged) == (46, 26, 46)
    # A car filling the view: the relative likelihood rests on what is left (the filter's kidnap.min_beams).
    most = np.where(np.arange(46) < 44, 0.3, ranges)
    assert model.evaluate(tracked, Scan(most, angles[0], step, 10.0), settled=truth).beams_judged == 2
    # Off (null), or with no settled belief: every beam counts.
    off = LikelihoodFieldModel(lmap, SensorModelConfig(beam_skip=False, unmapped_margin_m=None), range_max=10.0)
    scan = Scan(blocked, angles[0], step, 10.0)
    np.testing.assert_allclose(off.evaluate(tracked, scan, settled=truth).relative_likelihood,
                               plain.relative_likelihood, rtol=1e-6)


def test_off_map_particles_get_finite_low_likelihoods(lmap):
    model = LikelihoodFieldModel(lmap, SensorModelConfig(), range_max=10.0)
    scan = Scan(np.full(60, 2.0), -2.0, 4.0 / 59, 10.0)
    res = model.evaluate(np.array([[1e6, -1e6, 0.3], [0.0, 0.0, 0.0], [np.float64(1e300), 0.0, 0.0]]), scan)
    assert np.all(np.isfinite(res.log_likelihood))
    assert res.log_likelihood[0] == pytest.approx(60 * model.log_floor, rel=1e-6)


def test_numba_and_numpy_field_sums_agree(lmap):
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-3, 7, 500), rng.uniform(-4, 4, 500), rng.uniform(-4, 4, 500)])
    r, a = rng.uniform(0.1, 12, 300), rng.uniform(-2.4, 2.4, 300)
    args = (poses, r * np.cos(a), r * np.sin(a), lmap.distance_padded, lmap.resolution, (lmap.origin_x, lmap.origin_y))
    fast = kernels.field_sum(*args, backend="auto")
    twin = kernels.field_sum(*args, backend="numpy")
    np.testing.assert_allclose(fast, twin, rtol=1e-5)


def test_split_field_sums_are_the_sums_over_each_part(lmap):
    rng = np.random.default_rng(5)
    poses = np.column_stack([rng.uniform(-3, 7, 300), rng.uniform(-4, 4, 300), rng.uniform(-4, 4, 300)])
    r, a = rng.uniform(0.1, 12, 50), rng.uniform(-2.4, 2.4, 50)
    bx, by = r * np.cos(a), r * np.sin(a)
    left_out = rng.random(50) < 0.3
    field, origin = lmap.distance_padded, (lmap.origin_x, lmap.origin_y)
    kept = kernels.field_sum(poses, bx[~left_out], by[~left_out], field, lmap.resolution, origin, backend="numpy")
    rest = kernels.field_sum(poses, bx[left_out], by[left_out], field, lmap.resolution, origin, backend="numpy")
    for backend in ("auto", "numpy"):
        fit, total = kernels.field_sums(poses, bx, by, left_out, field, lmap.resolution, origin, backend=backend)
        np.testing.assert_allclose(fit, kept, rtol=1e-5)
        np.testing.assert_allclose(total, kept + rest, rtol=1e-5)
    fit, total = kernels.field_sums(poses, bx, by, None, field, lmap.resolution, origin)
    np.testing.assert_allclose(fit, kept + rest, rtol=1e-5)
    np.testing.assert_array_equal(fit, total)


def test_numba_and_numpy_beam_agreement_agree_with_a_brute_force_count(lmap):
    rng = np.random.default_rng(4)
    poses = np.column_stack([rng.uniform(-3, 7, 700), rng.uniform(-4, 4, 700), rng.uniform(-4, 4, 700)])
    r, a = rng.uniform(0.1, 12, 40), rng.uniform(-2.4, 2.4, 40)
    bx, by = r * np.cos(a), r * np.sin(a)
    origin = (lmap.origin_x, lmap.origin_y)
    fast = kernels.beam_agreement(poses, bx, by, lmap.distance_padded, 0.5, lmap.resolution, origin)
    twin = kernels.beam_agreement(poses, bx, by, lmap.distance_padded, 0.5, lmap.resolution, origin, backend="numpy")
    # Independent twin: the endpoints in the map frame, looked up through the map's own world-to-cell.
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    ex, ey = poses[:, 0:1] + c * bx - s * by, poses[:, 1:2] + s * bx + c * by
    near = lmap.distance_at(ex, ey) < 0.5
    np.testing.assert_allclose(fast, twin, atol=1e-12)
    np.testing.assert_allclose(fast, near.mean(axis=0), atol=2 / len(poses))  # cell-boundary rounding
    assert np.any((fast > 0) & (fast < 1))  # a test with something to count


def test_ray_casting_matches_brute_force_marching():
    occ = box_map()
    occ.grid[40:45, 30:90] = OCCUPIED  # a bar across the room
    occ.grid[10:60, 100] = OCCUPIED  # a one-cell-thick wall
    lm = LaserMap.from_occupancy(occ, 2.0)
    rng = np.random.default_rng(4)
    poses = lm.sample_free(12, rng)
    angles = np.linspace(-2.3, 2.3, 45)
    fast = kernels.cast_rays(poses, angles, lm.occupied, kernels.safe_steps(lm.occupied), lm.resolution,
                             (lm.origin_x, lm.origin_y), 8.0)
    brute = cast_rays_brute(poses, angles, lm.occupied, lm.resolution, (lm.origin_x, lm.origin_y), 8.0)
    assert np.abs(fast - brute).max() < 0.01 * lm.resolution + 1e-9


def test_beam_model_mixture_integrates_to_one():
    lm = LaserMap.from_occupancy(box_map(), 2.0)
    cfg = SensorModelConfig(model="beam", z_hit=0.7, z_short=0.1, z_max=0.1, z_rand=0.1, sigma_hit=0.2,
                            lambda_short=0.5)
    model = BeamModel(lm, cfg, range_max=10.0)

    def density(z):
        return float(model.probabilities(np.array([z]), np.array([4.0]))[0])

    mass = quad(density, 0, 10.0, points=[4.0], limit=200)[0] + float(model.probabilities(np.array([10.0]),
                                                                                        np.array([4.0]))[0])
    assert mass == pytest.approx(1.0, abs=1e-3)


def test_beam_model_prefers_the_true_pose(lmap):
    cfg = SensorModelConfig(model="beam", max_beams=30)
    model = BeamModel(lmap, cfg, range_max=10.0)
    angles = np.linspace(-2.3, 2.3, 30)
    true = np.array([[1.0, 0.5, 0.4]])
    ranges = model.expected(true, angles)[0]
    scan = Scan(ranges, -2.3, 4.6 / 29, 10.0)
    others = np.array([[1.3, 0.5, 0.4], [1.0, 0.5, 0.6], [3.0, -1.0, 2.0]])
    res = model.evaluate(np.vstack([true, others]), scan)
    assert np.argmax(res.log_likelihood) == 0 and res.relative_likelihood[0] == pytest.approx(1.0, abs=0.05)


def test_range_table_matches_marching_at_cell_centres_and_bin_headings(tmp_path, monkeypatch):
    monkeypatch.setenv("SITELOC_CACHE", str(tmp_path))
    occ = box_map()
    occ.grid[40:45, 30:90] = OCCUPIED
    lm = LaserMap.from_occupancy(occ, 2.0)
    cfg_t = SensorModelConfig(model="beam", max_beams=40, ray_cast="table", table_angles=72)
    cfg_m = cfg_t.model_copy(update={"ray_cast": "march"})
    table_model, march_model = BeamModel(lm, cfg_t, 10.0), BeamModel(lm, cfg_m, 10.0)
    assert list(tmp_path.glob("range-tables/*.npz"))  # cached on disk, and read back identically
    from pipeline.runtime import sensor

    sensor._TABLES.clear()
    np.testing.assert_array_equal(BeamModel(lm, cfg_t, 10.0).table[1], table_model.table[1])
    rng = np.random.default_rng(5)
    free = lm.sample_free(30, rng)
    width = 2 * math.pi / 72
    # Particles exactly at cell centres, headed so that every beam points at a bin centre: both paths agree.
    row, col = lm.cells(free[:, 0], free[:, 1])
    centres = np.column_stack([lm.origin_x + (col + 0.5) * lm.resolution, lm.origin_y + (row + 0.5) * lm.resolution,
                               -math.pi + (rng.integers(0, 72, 30) + 0.5) * width])
    angles = np.arange(-18, 18) * width
    scan = Scan(march_model.expected(centres[:1], angles)[0] + 0.03, angles[0], width, 10.0)
    cell_index, table, unit = table_model.table
    bins = np.floor((centres[:, 2:3] + angles + math.pi) % (2 * math.pi) / width).astype(int)
    looked_up = table[cell_index[row, col][:, None], bins] * unit
    np.testing.assert_allclose(looked_up, march_model.expected(centres, angles), atol=unit)  # uint16 rounding only
    np.testing.assert_allclose(table_model.evaluate(centres, scan).log_likelihood,
                               march_model.evaluate(centres, scan).log_likelihood, rtol=1e-4, atol=1e-2)
    # Elsewhere the table is within a cell and a bin of the exact answer: the true pose still wins.
    true = np.array([[1.03, 0.47, 0.41]])
    real = Scan(march_model.expected(true, angles)[0], angles[0], width, 10.0)
    others = np.array([[1.4, 0.47, 0.41], [1.03, 0.47, 0.7], [3.0, -1.0, 2.0]])
    assert np.argmax(table_model.evaluate(np.vstack([true, others]), real).log_likelihood) == 0
