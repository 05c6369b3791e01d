"""The laser-only campus: its map, its drive and its scans, checked against brute-force twins."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.io.map_yaml import read_map
from pipeline.io.tables import read_table
from pipeline.sitegen.campus import drive, generate_campus
from pipeline.sitegen.synth_laser import load_laser_preset, run_synth_laser
from stages.app import app

SMALL = {"size": [100, 90], "blocks": [2, 2], "street_width": 12.0, "wing_depth": 8.0, "route_length": 150.0,
         "resolution": 0.1, "parked_cars": 4, "kinds": {"building": 1, "courtyard": 1, "plaza": 1}}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    p = load_laser_preset("campus", SMALL)
    return p, run_synth_laser(p, outputs={"out": tmp_path_factory.mktemp("campus") / "c"}, progress=False)


def _cells(occ, xy):
    r, c = occ.world_to_cell(xy[:, 0], xy[:, 1])
    return r, c


def test_map_has_facades_unknown_interiors_and_a_free_drive(site):
    p, out = site
    campus = generate_campus(p)
    occ = read_map(out / "map.yaml")
    assert np.array_equal(occ.grid, campus.map.grid)
    assert occ.occupied.any() and (occ.grid == -1).any() and occ.free.mean() > 0.5
    # Every unknown (interior) cell is enclosed: its 4 neighbours are unknown or occupied, never free.
    unknown = occ.grid == -1
    free = occ.free
    assert not (unknown[1:, :] & free[:-1, :]).any() and not (unknown[:, 1:] & free[:, :-1]).any()
    cols = read_table(out / "runs" / "campus.parquet", "runs").to_pydict()
    gt = np.column_stack([cols["gt_x"], cols["gt_y"], cols["gt_theta"]])
    r, c = _cells(campus.world, gt[:, :2])
    assert campus.world.free[r, c].all()  # the drive never enters a wall, a tree or a car
    steps = np.hypot(*np.diff(gt[:, :2], axis=0).T)
    # A scan every 0.9 m of path: straight stretches exactly, a corner's chord shorter.
    assert np.all(steps <= p.scan_every_m + 1e-6) and np.mean(np.isclose(steps, p.scan_every_m)) > 0.9
    assert len(gt) * p.scan_every_m >= p.route_length - p.scan_every_m


def _brute_range(world, pose, angle, range_max, step=0.01):
    """Distance to the first occupied cell along a ray, by small steps (the twin of the sphere tracer)."""
    d = np.arange(0.0, range_max + step, step)
    x, y = pose[0] + d * np.cos(pose[2] + angle), pose[1] + d * np.sin(pose[2] + angle)
    r, c = world.world_to_cell(x, y)
    inside = world.contains(r, c)
    hit = np.zeros(len(d), bool)
    hit[inside] = world.occupied[r[inside], c[inside]]
    hit |= ~inside  # leaving the grid: no return
    k = int(np.argmax(hit)) if hit.any() else len(d)
    return np.inf if k == len(d) or not inside[k] else d[k]


def test_scans_and_their_no_returns_match_a_brute_force_twin(site):
    p, out = site
    campus = generate_campus(p)
    cols = read_table(out / "runs" / "campus.parquet", "runs").to_pydict()
    gt = np.column_stack([cols["gt_x"], cols["gt_y"], cols["gt_theta"]])
    ranges = np.array(cols["ranges"], np.float32)
    angles = cols["angle_min"][0] + cols["angle_increment"][0] * np.arange(ranges.shape[1])
    rng = np.random.default_rng(0)
    returns_ok, returns, missing, no_returns = 0, 0, 0, 0
    for t, b in zip(rng.integers(0, len(gt), 300), rng.integers(0, ranges.shape[1], 300), strict=True):
        true = _brute_range(campus.world, gt[t], angles[b], p.laser.range_max)
        if ranges[t, b] >= p.laser.range_max:  # no return: beyond range, or a dropout
            no_returns += 1
            missing += true < p.laser.range_max - 2 * p.resolution
        else:
            returns += 1
            returns_ok += abs(ranges[t, b] - true) < 4 * p.laser.noise_sigma + 2 * p.resolution
    assert returns_ok == returns and returns > 50 and no_returns > 50
    assert missing <= max(3, 3 * p.laser.dropout * 300)  # only the dropouts return nothing short of range
    report = json.loads((out / "report.json").read_text())
    assert report["no_return_share"] == pytest.approx(float((ranges >= p.laser.range_max).mean()), abs=1e-4)
    assert 0.2 < report["no_return_share"] < 0.8  # a sparse site: many beams return nothing
    assert report["endpoint_on_occupied_share_tol1"] > 0.85  # on the map's walls and trees (cars are not)


def test_drive_is_seeded_and_outputs_are_byte_identical(site, tmp_path):
    p, out = site
    again = run_synth_laser(p, outputs={"out": tmp_path / "again"}, progress=False)
    for name in ("map.pgm", "map.yaml", "runs/campus.parquet", "report.json", "preview.png", "preset.yaml"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), name
    other = load_laser_preset("campus", {**SMALL, "seed": 1})
    a = drive(generate_campus(p), p, np.random.default_rng(1))
    b = drive(generate_campus(other), other, np.random.default_rng(1))
    assert a.shape != b.shape or not np.allclose(a, b)


def test_cli_writes_the_site_and_localize_tracks_it(tmp_path):
    runner = CliRunner()
    sets = [a for k, v in SMALL.items() for a in ("--set", f"{k}={json.dumps(v)}")]
    res = runner.invoke(app, ["synth-laser", "--out", str(tmp_path / "c"), *sets, "--set", "route_length=60"])
    assert res.exit_code == 0, res.output
    assert "no return" in res.output and (tmp_path / "c" / "preview.png").stat().st_size > 10_000
    res = runner.invoke(app, ["localize", str(tmp_path / "c"), "--out", str(tmp_path / "loc"), "--init", "pose",
                              "--config", "ci"])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "loc" / "metrics.json").read_text())
    assert m["runs"]["campus"][0]["converged_step"] == 0


def test_bad_presets_fail_clearly(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["synth-laser", "--out", str(tmp_path / "a"), "--set", "blocks=[9,9]"])
    assert res.exit_code == 1 and "blocks" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["synth-laser", "--out", str(tmp_path / "b"), "--set", "colour=red"])
    assert res.exit_code == 1 and "colour" in res.output
    res = runner.invoke(app, ["synth-laser", "--out", str(tmp_path / "c"), "--preset", "nowhere"])
    assert res.exit_code == 1 and "campus" in res.output
    assert not any((tmp_path / n).exists() for n in "abc")
