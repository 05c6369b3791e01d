"""Retrieved poses checked against the scan (`pipeline.runtime.scancheck`)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import FilterConfig
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.scancheck import check_candidates
from pipeline.runtime.sensor import Scan, make_sensor_model
from pipeline.sitegen.laser import LaserScanner, rasterise_map
from pipeline.sitegen.trajectories import sample_stops
from tests.sitegen.small_floor import small_floor

RANGE_MAX = 30.0


@pytest.fixture(scope="module")
def world():
    scene = small_floor()
    occ = rasterise_map(scene)
    cfg = FilterConfig()
    lmap = LaserMap.from_occupancy(occ, cfg.sensor.max_distance)
    sensor = make_sensor_model(lmap, cfg.sensor, RANGE_MAX)
    scanner = LaserScanner(occ, beams=271, fov_deg=270, range_max=RANGE_MAX, seed=1)
    stops = np.array([s[:2] for s in sample_stops(scene, occ, spacing=2.0, clearance=0.45, jitter=0.3, seed=4)])
    return lmap, sensor, scanner, stops


def scan_at(scanner, pose) -> Scan:
    ranges = scanner.cast_many(np.asarray(pose, dtype=np.float64)[None])[0]
    return Scan(ranges, scanner.angle_min, scanner.angle_increment, RANGE_MAX)


def test_the_true_place_is_picked_from_decoys_and_refined(world):
    lmap, sensor, scanner, stops = world
    truth = np.array([*stops[3, :2], 0.7])
    scan = scan_at(scanner, truth)
    rng = np.random.default_rng(0)
    # Retrieval ranked the truth (0.4 m and 10 degrees off) ninth, behind decoys at other stops.
    decoys = np.column_stack([stops[[10, 20, 12, 5, 15, 18, 21, 0], :2], rng.uniform(-np.pi, np.pi, 8)])
    near = truth + np.array([0.3, -0.25, np.radians(10)])
    retrieved = np.vstack([decoys, near])
    got = check_candidates(sensor, lmap, retrieved, scan, keep=4, samples=128, std_xy=0.5,
                           std_theta=np.radians(15), rng=np.random.default_rng(1))
    assert got.rank[0] == 8
    # The best perturbation is nearer the truth than the retrieved pose it came from.
    assert np.hypot(*(got.poses[0, :2] - truth[:2])) < np.hypot(*(near[:2] - truth[:2]))
    # Scores are the sensor's own, in descending order; the kept poses are free.
    again = sensor.evaluate(got.poses, scan)
    np.testing.assert_allclose(got.log_likelihood, again.log_likelihood, rtol=1e-6)
    np.testing.assert_allclose(got.relative_likelihood, again.relative_likelihood, rtol=1e-6)
    assert np.all(np.diff(got.log_likelihood) <= 0)
    assert len(set(got.rank.tolist())) == 4


def test_a_candidates_score_is_the_best_of_its_perturbations(world):
    """Brute-force twin: the same draws scored one candidate at a time."""
    lmap, sensor, scanner, stops = world
    scan = scan_at(scanner, [*stops[7, :2], -1.2])
    retrieved = np.column_stack([stops[[7, 8, 9], :2], [-1.0, 0.0, 2.0]])
    samples, std = 16, np.radians([15.0, 180.0, 15.0])
    got = check_candidates(sensor, lmap, retrieved, scan, keep=3, samples=samples, std_xy=0.5, std_theta=std,
                           rng=np.random.default_rng(5))
    rng = np.random.default_rng(5)
    poses = lmap.jitter(np.repeat(retrieved, samples, axis=0), 0.5, np.repeat(std, samples), rng)
    poses[::samples] = retrieved
    ll = sensor.evaluate(poses, scan).log_likelihood.reshape(3, samples)
    for rank, score in zip(got.rank, got.log_likelihood, strict=True):
        assert score == pytest.approx(ll[rank].max(), rel=1e-9)


def test_refinement_rounds_never_score_lower_and_close_in_on_the_truth(world):
    """Round one draws what a single round draws (same generator), and each later round keeps the best so
    far among its draws: every candidate's score can only rise; the truth's pose ends up closer."""
    lmap, sensor, scanner, stops = world
    truth = np.array([*stops[5, :2], 0.4])
    scan = scan_at(scanner, truth)
    retrieved = np.vstack([truth + [0.35, -0.3, np.radians(12)], [*stops[14, :2], 2.0], [*stops[2, :2], -1.0]])
    kw = dict(keep=3, samples=24, std_xy=0.5, std_theta=np.radians(15))
    one = check_candidates(sensor, lmap, retrieved, scan, rng=np.random.default_rng(3), rounds=1, **kw)
    four = check_candidates(sensor, lmap, retrieved, scan, rng=np.random.default_rng(3), rounds=4, **kw)
    by_rank = {r: s for r, s in zip(one.rank, one.log_likelihood, strict=True)}
    for rank, score in zip(four.rank, four.log_likelihood, strict=True):
        assert score >= by_rank[rank] - 1e-9
    i1, i4 = int(np.nonzero(one.rank == 0)[0][0]), int(np.nonzero(four.rank == 0)[0][0])
    assert np.hypot(*(four.poses[i4, :2] - truth[:2])) <= np.hypot(*(one.poses[i1, :2] - truth[:2]))
    assert np.hypot(*(four.poses[i4, :2] - truth[:2])) < 0.15
    # The scores are the sensor's own at the returned poses.
    np.testing.assert_allclose(four.log_likelihood, sensor.evaluate(four.poses, scan).log_likelihood, rtol=1e-6)


def test_rank_prior_orders_equal_fits_by_retrieval_and_yields_to_a_clearly_better_fit(world):
    lmap, sensor, scanner, stops = world
    truth = np.array([*stops[6, :2], -0.8])
    scan = scan_at(scanner, truth)
    kw = dict(keep=3, samples=1, std_xy=0.5, std_theta=0.2)  # one sample: the retrieved pose itself
    # The same pose three times fits identically; the prior alone orders them, by retrieval rank.
    same = np.repeat(truth[None], 3, axis=0)
    prior = -np.log1p(np.array([2.0, 0.0, 1.0]))
    got = check_candidates(sensor, lmap, same, scan, rng=np.random.default_rng(0), log_prior=prior, **kw)
    assert got.rank.tolist() == [1, 2, 0]
    # A far pose ranked first by retrieval does not beat the truth's fit for a log(2) prior.
    far = np.vstack([[*stops[15, :2], 1.0], truth])
    got = check_candidates(sensor, lmap, far, scan, rng=np.random.default_rng(0), log_prior=-np.log1p([0.0, 1.0]),
                           **kw)
    assert got.rank[0] == 1
    assert got.log_likelihood[0] - got.log_likelihood[1] > np.log(2.0)


def test_without_usable_beams_retrieval_order_stands(world):
    lmap, sensor, scanner, stops = world
    empty = Scan(np.full(271, np.inf), scanner.angle_min, scanner.angle_increment, RANGE_MAX)
    got = check_candidates(sensor, lmap, np.column_stack([stops[:5, :2], np.zeros(5)]), empty, keep=4, samples=8,
                           std_xy=0.5, std_theta=0.2, rng=np.random.default_rng(0))
    assert got is None
    with pytest.raises(ValueError, match="no retrieved poses"):
        check_candidates(sensor, lmap, np.zeros((0, 3)), empty, keep=4, samples=8, std_xy=0.5, std_theta=0.2,
                         rng=np.random.default_rng(0))


def test_jitter_spreads_each_pose_by_its_own_heading_std(world):
    lmap, _, _, stops = world
    base = np.repeat(np.column_stack([stops[:2, :2], [0.0, 0.0]]), 4000, axis=0)
    std = np.repeat([0.05, 1.0], 4000)
    out = lmap.jitter(base, 0.2, std, np.random.default_rng(2))
    assert lmap.is_free(out[:, 0], out[:, 1]).all()
    spread = [np.std(out[:4000, 2]), np.std(out[4000:, 2])]
    assert spread[0] == pytest.approx(0.05, rel=0.1) and spread[1] == pytest.approx(1.0, rel=0.1)
    # One scalar spread draws exactly what sample_around always drew.
    a = lmap.sample_around(base[:3], np.ones(3), 50, 0.3, 0.2, np.random.default_rng(9))
    rng = np.random.default_rng(9)
    which = rng.choice(3, size=50, p=np.full(3, 1 / 3))
    np.testing.assert_array_equal(a, lmap.jitter(base[:3][which], 0.3, 0.2, rng))


def test_the_beam_verifier_keeps_the_truth_first_when_people_block_the_laser(world):
    """Two people close to the laser (two sectors of short readings): the likelihood field scores their
    returns as misses, so at several stops a decoy elsewhere fits better; the beam model explains them as
    short readings and keeps the truth first at every stop (`scan_check.model: beam`)."""
    lmap, sensor, scanner, stops = world
    beam = make_sensor_model(lmap, FilterConfig().sensor.model_copy(update={"model": "beam"}), RANGE_MAX)
    first = {"field": 0, "beam": 0}
    tested = range(0, len(stops), 3)
    for k in tested:
        truth = np.array([*stops[k, :2], 0.7])
        scan = scan_at(scanner, truth)
        ranges = scan.ranges.copy()
        ranges[60:110] = np.minimum(ranges[60:110], 0.7)
        ranges[170:220] = np.minimum(ranges[170:220], 1.1)
        blocked = Scan(ranges, scan.angle_min, scan.angle_increment, RANGE_MAX)
        decoys = np.column_stack([np.delete(stops[:, :2], k, 0), np.random.default_rng(0).uniform(-np.pi, np.pi,
                                                                                                   len(stops) - 1)])
        pool = np.vstack([truth + np.array([0.2, -0.2, 0.1]), decoys])
        for name, model in (("field", sensor), ("beam", beam)):
            got = check_candidates(model, lmap, pool, blocked, keep=len(pool), samples=64, std_xy=0.5,
                                   std_theta=np.radians(15), rng=np.random.default_rng(1), rounds=3)
            first[name] += int(got.rank[0] == 0)
    assert first["beam"] == len(tested)
    assert first["field"] <= len(tested) - 2, first
