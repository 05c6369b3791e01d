"""The filter on a small generated floor: global convergence, kidnap recovery, candidates, robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.config import FilterConfig
from pipeline.runtime.amcl import AdaptiveMCL, FilterState
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.sensor import Scan
from pipeline.sitegen.laser import LaserScanner, rasterise_map
from pipeline.sitegen.trajectories import make_runs, sample_stops
from tests.sitegen.small_floor import small_floor

RANGE_MAX = 30.0


@pytest.fixture(scope="module")
def world():
    scene = small_floor()
    occ = rasterise_map(scene)
    stops = sample_stops(scene, occ, spacing=2.0, clearance=0.45, jitter=0.3, seed=4)
    runs = make_runs(scene, occ, stops, n_mapping=1, n_query=1, steps_per_run=120, step=0.3,
                     kidnaps_per_query_run=1, seed=5)
    scanner = LaserScanner(occ, beams=271, fov_deg=270, range_max=RANGE_MAX, seed=1)
    scans = {r.name: scanner.cast_many(r.gt) for r in runs}
    return occ, {r.name: r for r in runs}, scans, scanner


def make(occ, **cfg) -> AdaptiveMCL:
    c = FilterConfig(**{"min_particles": 300, "max_particles": 3000, **cfg})
    return AdaptiveMCL(LaserMap.from_occupancy(occ, c.sensor.max_distance), c, range_max=RANGE_MAX)


def scan_of(scanner, ranges) -> Scan:
    return Scan(ranges, scanner.angle_min, scanner.angle_increment, RANGE_MAX)


def replay(f: AdaptiveMCL, run, ranges, scanner, start=0, stop=None, on_step=None):
    errors, states, counts = [], [], []
    for i in range(start, stop or len(run.gt)):
        r = f.update(run.odom[i], scan_of(scanner, ranges[i]))
        w = f.weights
        assert np.all(np.isfinite(f.particles)) and np.all(np.isfinite(w)) and w.sum() == pytest.approx(1.0)
        errors.append(math.hypot(*(r.pose[:2] - run.gt[i, :2])))
        states.append(r.state)
        counts.append(r.particles)
        if on_step:
            on_step(i, f, r)
    return np.array(errors), states, np.array(counts)


def test_global_localization_converges_from_uniform(world):
    occ, runs, scans, scanner = world
    f = make(occ)
    f.init_uniform()
    run = runs["mapping_00"]
    errors, states, counts = replay(f, run, scans["mapping_00"], scanner)
    assert np.all(errors[-40:] < 0.25), errors[-40:]
    assert states[-1] == FilterState.TRACKING
    assert counts[-1] < 1000  # KLD keeps few particles once the belief is tight ...
    unsure = make(occ)
    unsure.init_uniform()
    for i in range(3):  # ... and many while the scans say nothing (every beam at max range)
        blank = scan_of(scanner, np.full(len(scans["mapping_00"][i]), RANGE_MAX))
        assert unsure.update(run.odom[i], blank).particles > 1000


def test_kidnapping_is_detected_and_recovered(world):
    occ, runs, scans, scanner = world
    run = runs["query_00"]
    (k,) = np.nonzero(run.kidnapped)[0]
    f = make(occ)
    f.init_pose(run.gt[0])
    errors, states, _ = replay(f, run, scans["query_00"], scanner)
    assert np.all(errors[:k] < 0.25)
    assert FilterState.LOST in states[k:k + 5]
    recovered = k + int(np.argmax(errors[k:] < 0.25))
    assert recovered - k <= 10 and np.all(errors[recovered + 3:] < 0.3)


def test_candidates_seed_and_injection_recover(world):
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]
    f = make(occ)
    wrong = [run.gt[0] + [3.0, 1.0, 1.0], run.gt[0] + [-4.0, 0.5, 2.0], run.gt[0] + [6.0, 0.0, 0.0]]
    f.init_candidates([wrong[0], run.gt[0], wrong[1], wrong[2]], [4, 3, 2, 1])  # the truth second: 3 of 10
    errors, _, _ = replay(f, run, ranges, scanner, stop=6)
    assert np.all(errors[2:] < 0.3)

    # Kidnapped, with no global restart: only the candidates injected while lost bring it back.
    run, ranges = runs["query_00"], scans["query_00"]
    (k,) = np.nonzero(run.kidnapped)[0]
    lost = make(occ, kidnap={"reinit_uniform": False}, method="kld")
    lost.init_pose(run.gt[0])
    injected = []

    def inject_when_lost(i, filt, res):
        if res.state == FilterState.LOST and i + 1 < len(run.gt):
            injected.append(filt.inject([run.gt[i + 1] + [0.3, -0.2, 0.1]]))

    errors, states, _ = replay(lost, run, ranges, scanner, on_step=inject_when_lost)
    assert injected and injected[0] == 1000
    assert states[-1] == FilterState.TRACKING and np.all(errors[k + 10:] < 0.3)


@pytest.mark.parametrize("method", ["mcl", "kld", "mixture"])
def test_baseline_methods_track(world, method):
    occ, runs, scans, scanner = world
    run = runs["mapping_00"]
    f = make(occ, method=method, max_particles=1000, min_particles=200)
    f.init_pose(run.gt[0])
    errors, _, counts = replay(f, run, scans["mapping_00"], scanner, stop=50)
    assert np.median(errors) < 0.15
    if method == "mcl":
        assert np.all(counts == 1000)


def test_beam_model_tracks(world):
    occ, runs, scans, scanner = world
    run = runs["mapping_00"]
    f = make(occ, sensor={"model": "beam"}, max_particles=1000)
    f.init_pose(run.gt[0])
    errors, _, _ = replay(f, run, scans["mapping_00"], scanner, stop=50)
    assert np.median(errors) < 0.15


def test_bad_input_is_survived(world):
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]
    f = make(occ)
    f.init_pose(run.gt[0])
    f.update(run.odom[0], scan_of(scanner, ranges[0]))
    n = len(ranges[1])
    for bad in (np.full(n, np.nan), np.full(n, np.inf), np.zeros(n), np.full(n, -np.inf), np.array([])):
        scan = Scan(bad, scanner.angle_min, scanner.angle_increment, RANGE_MAX)
        r = f.update(run.odom[1] + [0.5, 0, 0], scan)
        assert np.all(np.isfinite(r.pose)) and np.isfinite(f.weights).all()
    assert not f.update(np.array([np.nan, 0.0, 0.0]), scan_of(scanner, ranges[2])).updated
    r = f.update(run.odom[2] + [1e6, -1e6, 40.0], scan_of(scanner, ranges[2]))  # a huge odometry jump
    assert np.all(np.isfinite(r.pose)) and np.isfinite(f.weights).all()
    f.particles[:10] = [[1e5, 1e5, 0.0]]  # particles far off the map
    r = f.update(run.odom[2] + [1e6 + 0.5, -1e6, 40.0], scan_of(scanner, ranges[3]))
    assert np.all(np.isfinite(r.pose))
    with pytest.raises(ValueError, match="weights"):
        f.inject([[0, 0, 0], [1, 1, 0]], weights=[1.0])


def test_updates_are_gated_and_seeded(world):
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]

    def go():
        f = make(occ)
        f.init_pose(run.gt[0])
        out = [f.update(run.odom[0], scan_of(scanner, ranges[0]))]
        out.append(f.update(run.odom[0] + [0.05, 0, 0], scan_of(scanner, ranges[0])))  # under update_min_d
        out += [f.update(run.odom[i], scan_of(scanner, ranges[i])) for i in range(1, 10)]
        return out

    a, b = go(), go()
    assert a[0].updated and not a[1].updated
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.pose, y.pose)


def test_a_crowd_in_front_of_the_laser_is_no_alarm_and_a_false_alarm_keeps_the_right_belief(world):
    """People all round the robot end every beam short of the map's walls: while the belief is settled
    that is no evidence of being lost (sensor.unmapped_margin_m, kidnap.min_beams). Scans that fit the
    map nowhere for a few updates (beams through its walls) do make the filter declare itself lost; the
    heaviest particles it keeps (kidnap.keep_particles) bring it straight back instead of a new search."""
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]
    f = make(occ, kidnap={"keep_particles": 100})
    f.init_pose(run.gt[0])
    errors, _, _ = replay(f, run, ranges, scanner, stop=20)
    assert errors[-1] < 0.2
    crowd = np.minimum(ranges[20], 0.4)  # a crowd a step away, all round
    for k in range(20, 25):
        assert f.update(run.odom[k], scan_of(scanner, crowd)).state == FilterState.TRACKING
    # Five steps on odometry alone leave the belief off by decimetres; the scans after the crowd bring it back.
    errors, _, _ = replay(f, run, ranges, scanner, start=25, stop=45)
    assert np.all(errors[-10:] < 0.3) and f.state == FilterState.TRACKING, errors
    # The same crowd while the filter is not tracking is evidence like any scan: the rule reads every beam.
    searching = make(occ, sensor={"unmapped_margin_m": None})
    searching.init_pose(run.gt[0])
    replay(searching, run, ranges, scanner, stop=20)
    k = 20
    while searching.state != FilterState.LOST:
        searching.update(run.odom[k], scan_of(scanner, crowd))
        k += 1
        assert k < 30, "with every beam counted, three blocked scans make it lost"

    k = 45
    while f.state != FilterState.LOST:
        through = np.where(ranges[k] < RANGE_MAX - 2, ranges[k] + 1.5, ranges[k])  # beyond every wall
        f.update(run.odom[k], scan_of(scanner, through))
        k += 1
        assert k < 55, "three scans through the walls must make it lost"
    near = np.hypot(*(f.particles[:, :2] - run.gt[k - 1, :2]).T) < 0.5
    assert len(f.particles) == f.cfg.max_particles and near.sum() >= 100
    errors, _, _ = replay(f, run, ranges, scanner, start=k, stop=k + 6)
    assert np.all(errors[2:] < 0.3), errors


def test_beams_are_skipped_only_while_the_belief_is_one_settled_cluster(world, monkeypatch):
    """`sensor.beam_skip` with `beam_skip_spread_m`: a tracked belief skips; the same belief while the
    filter is not tracking, or with particles injected at a far candidate (the minority's beams are the
    evidence for it), does not; with the gate off (null) it skips whatever the belief, as nav2 does."""
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]
    used = []

    def track(**sensor):
        f = make(occ, sensor={"beam_skip": True, **sensor})
        f.init_pose(run.gt[0])
        replay(f, run, ranges, scanner, stop=5)
        monkeypatch.setattr(f.sensor, "evaluate_skipping",
                            lambda *a, **k: used.append("skip") or f.sensor.evaluate(*a, **k))
        return f

    f = track()
    assert f.state == FilterState.TRACKING and f._skips_beams()
    f.state = FilterState.RELOCALISING  # a search that has just collapsed onto one cluster still uses every beam
    assert not f._skips_beams()
    f.state = FilterState.TRACKING
    f.update(run.odom[5], scan_of(scanner, ranges[5]))
    assert used == ["skip"]
    f.inject([run.gt[5] + [6.0, 0.0, 0.0]])
    assert not f._skips_beams()
    used.clear()
    f.update(run.odom[6], scan_of(scanner, ranges[6]))
    assert used == []
    nav2 = track(beam_skip_spread_m=None)
    nav2.inject([run.gt[5] + [6.0, 0.0, 0.0]])
    assert nav2._skips_beams()
    assert not make(occ, sensor={"beam_skip": False})._skips_beams()
    assert not make(occ, sensor={"model": "beam"})._skips_beams()  # the beam model never skips


def test_random_particles_carry_no_evidence_into_the_average_likelihood(world, monkeypatch):
    """Augmented MCL: w_avg is the belief's average scan likelihood. The particles the last resampling
    drew at random over the map are left out of it (and of the beam-skip spread) until weighed: counting
    them lowers w_fast, which draws more of them, until a large map's few particles are mostly noise."""
    occ, runs, scans, scanner = world
    run, ranges = runs["mapping_00"], scans["mapping_00"]
    f = make(occ, sensor={"beam_skip": False})
    f.init_pose(run.gt[0])
    replay(f, run, ranges, scanner, stop=10)
    f.w_slow, f.w_fast = 1.0, 0.5  # p_random = 0.5 at the next resampling
    f.update(run.odom[10], scan_of(scanner, ranges[10]))
    fresh = f._fresh.copy()
    assert 0.35 < fresh.mean() < 0.65
    assert np.median(np.hypot(*(f.particles[fresh, :2] - run.gt[10, :2]).T)) > 2.0  # spread over the floor
    seen = {}
    evaluate = f.sensor.evaluate

    def spy(particles, scan, settled=None):
        seen["res"] = evaluate(particles, scan, settled=settled)
        return seen["res"]

    monkeypatch.setattr(f.sensor, "evaluate", spy)
    prior, w_fast = f.weights.copy(), f.w_fast
    f.update(run.odom[11], scan_of(scanner, ranges[11]))
    rel = seen["res"].relative_likelihood
    informed = ~fresh
    w_avg = prior[informed] @ rel[informed] / prior[informed].sum()
    assert f.w_fast == pytest.approx(w_fast + f.cfg.alpha_fast * (w_avg - w_fast))
    assert prior @ rel < 0.8 * w_avg  # with the random draws counted, the average would have fallen


def test_the_particle_budget_grows_with_the_free_space_of_a_large_site():
    """filter.max_particles_per_ha: a floor keeps max_particles; a 2.25 ha open site gets 4500 per hectare."""
    from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap

    grid = np.full((302, 302), FREE, dtype=np.int8)  # 0.5 m cells: 150 x 150 m of free space inside a wall
    grid[0], grid[-1], grid[:, 0], grid[:, -1] = OCCUPIED, OCCUPIED, OCCUPIED, OCCUPIED
    site = LaserMap.from_occupancy(OccupancyMap(grid, 0.5, 0.0, 0.0), 2.0)
    assert site.free_area_m2 == pytest.approx(150.0 * 150.0)
    big = AdaptiveMCL(site, FilterConfig(), range_max=RANGE_MAX)
    assert big.max_particles == math.ceil(4500 * 2.25) and len(big.particles) == big.max_particles
    big.init_uniform()
    assert len(big.particles) == 10125
    assert AdaptiveMCL(site, FilterConfig(max_particles_per_ha=None), range_max=RANGE_MAX).max_particles == 5000
    small = LaserMap.from_occupancy(OccupancyMap(grid[:40, :40].copy(), 0.5, 0.0, 0.0), 2.0)
    assert AdaptiveMCL(small, FilterConfig(), range_max=RANGE_MAX).max_particles == 5000
