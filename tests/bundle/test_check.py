"""`siteloc check`: a bundle against the building as it is now; drift found where it happened, nowhere else."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.compute as pc
import pytest
from typer.testing import CliRunner

from pipeline.bundle.check import map_drift, place_likeness, run_check
from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap, read_map
from pipeline.retrieval.metrics import positives
from pipeline.update.areas import cell_owners, stops_of
from stages.app import app
from tests.fixtures.recapture import lone_database_stop, mirrored_stop


def test_the_bundle_ships_its_stops_and_a_baseline_the_localizer_reproduces(micro_bundle):
    from pipeline.runtime.localizer import Localizer

    _, ing, _, index, bundle = micro_bundle
    stops = tables.read_table(bundle / "db" / "images.parquet", "images")
    catalog = tables.read_table(index / "catalog.parquet", "catalog")
    assert sorted(stops.column("image_id").to_pylist()) == sorted(catalog.column("image_id").to_pylist())
    base = json.loads((bundle / "evaluation" / "baseline.json").read_text())
    images = tables.read_table(ing / "images.parquet", "images")
    held = images.filter(pc.equal(images.column("split"), "test"))
    assert base["all"]["images"] == held.num_rows == sum(a["images"] for a in base["areas"].values())
    # Twin: the robot's own retrieval path (Localizer.retrieved) gives the same recall@1.
    loc = Localizer.from_bundle(bundle)
    cols = held.select(["image_id", "x", "y", "theta"]).to_pydict()
    hits = []
    for iid, x, y, th in zip(*cols.values(), strict=True):
        top = loc.retrieved(ing / iid)[:1]
        hits.append(bool(positives(np.array([[x, y, th]]), top, 2.0, 30.0).any()))
    assert base["all"]["recall_at_1"] == pytest.approx(np.mean(hits))


def test_the_unchanged_site_shows_no_drift(micro_bundle, tmp_path):
    cfg, ing, _, _, bundle = micro_bundle
    out = run_check(cfg, inputs={"bundle": bundle, "data": ing}, outputs={"out": tmp_path / "c"}, localize=False,
                    progress=False)
    doc = json.loads((out / "report.json").read_text())
    assert doc["recommendation"]["recapture"] == [] and doc["recommendation"]["update_map"] == []
    judged = [e for e in doc["areas"].values() if e["verdict"] != "too few data"]
    assert judged and all(e["verdict"] == "ok" for e in judged)
    # The database's own views, captured again unchanged, are identical to the bundle's at their place.
    assert all(e["place_likeness"] == 1.0 for e in judged if "place_likeness" in e)
    assert all(e["changed_view_share"] == 0.0 for e in judged if "place_likeness" in e)
    assert doc["map"]["endpoint_share_on_walls"] > 0.9 and doc["map"]["scans"] > 0
    assert {p.name for p in out.iterdir()} >= {"report.json", "report.md", "drift.png", "config.yaml"}


def test_a_changed_stop_is_flagged_and_nothing_else(micro_bundle, tmp_path):
    cfg, ing, _, _, bundle = micro_bundle
    stop, key = lone_database_stop(bundle)
    new = mirrored_stop(ing, tmp_path / "new", stop)
    out = run_check(cfg, inputs={"bundle": bundle, "data": new}, outputs={"out": tmp_path / "c"}, localize=False,
                    progress=False)
    doc = json.loads((out / "report.json").read_text())
    assert doc["recommendation"]["recapture"] == [key], doc["recommendation"]
    assert doc["areas"][key]["place_likeness"] < cfg.check.min_place_likeness
    assert "Re-capture " + key in (out / "report.md").read_text()


def test_an_area_is_re_captured_when_more_than_a_share_of_its_views_changed(micro_bundle, tmp_path):
    cfg, ing, _, _, bundle = micro_bundle
    stop, key = lone_database_stop(bundle)
    reports = {}
    for views in (1, 2):  # of 6: 17 % and 33 %, either side of check.max_changed_views (20 %)
        new = mirrored_stop(ing, tmp_path / f"new{views}", stop, views=views)
        out = run_check(cfg, inputs={"bundle": bundle, "data": new}, outputs={"out": tmp_path / f"c{views}"},
                        localize=False, progress=False)
        reports[views] = json.loads((out / "report.json").read_text())
        area = reports[views]["areas"][key]
        assert area["new"]["same_place_changed"] == views and area["new"]["same_place_images"] == 6
        assert area["changed_view_share"] == pytest.approx(views / 6, abs=1e-4)
        # The median view is unchanged either way: the median alone would call both areas alike.
        assert area["place_likeness"] == 1.0
    assert cfg.check.max_changed_views == 0.2
    assert reports[1]["recommendation"]["recapture"] == []
    assert reports[2]["recommendation"]["recapture"] == [key]
    assert "2 of 6 views (33%) unlike the bundle's" in reports[2]["areas"][key]["reasons"][0]


def test_place_likeness_is_one_for_the_same_view_and_zero_at_a_neighbours():
    assert place_likeness(1.0, 0.3) == 1.0 and place_likeness(0.3, 0.3) == 0.0 and place_likeness(0.1, 0.3) == 0.0
    assert place_likeness(0.65, 0.3) == pytest.approx(0.5)


def test_map_drift_finds_a_wall_gone_and_a_new_obstacle_in_their_areas_only(micro_bundle):
    cfg, ing, _, _, bundle = micro_bundle
    import yaml

    occ = read_map(bundle / "map" / "map.yaml")
    mount = tuple(yaml.safe_load((bundle / "filter.yaml").read_text())["laser"]["base_from_laser"])
    runs = [tables.read_table(p, "runs") for p in sorted((ing / "runs").glob("*.parquet"))]
    stops = stops_of(tables.read_table(bundle / "db" / "images.parquet", "images"))
    owner, names = cell_owners(occ, stops.xy, stops.keys())
    base = map_drift(occ, owner, names, runs, mount, cfg, progress=False)
    assert base["new_obstacle_cells"] == 0 and base["walls_gone_cells"] == 0
    # Edit the map as a building changes the other way: a block of wall the scans see is erased (the
    # scans now see an obstacle the map lacks), and a block is added in free space the scans cross.
    endpoints = _hit_cells(occ, runs, mount)
    wall_cells = np.argwhere(endpoints & (occ.grid == OCCUPIED))
    r0, c0 = wall_cells[len(wall_cells) // 2]
    grid = occ.grid.copy()
    erase = np.zeros_like(grid, dtype=bool)
    erase[max(r0 - 4, 0):r0 + 5, max(c0 - 4, 0):c0 + 5] = True
    erase &= grid == OCCUPIED
    grid[erase] = FREE
    crossed = np.argwhere((base_seen := _seen_free(occ, runs, cfg, mount)) & (owner != owner[r0, c0]))
    r1, c1 = crossed[len(crossed) // 2]
    block = np.zeros_like(erase)
    block[r1 - 2:r1 + 3, c1 - 2:c1 + 3] = True
    block &= base_seen
    grid[block] = OCCUPIED
    edited = OccupancyMap(grid=grid, resolution=occ.resolution, origin_x=occ.origin_x, origin_y=occ.origin_y,
                          origin_yaw=occ.origin_yaw)
    d = map_drift(edited, owner, names, runs, mount, cfg, progress=False)
    assert d["new_obstacle_cells"] > 0 and d["walls_gone_cells"] > 0
    assert np.all(erase[d["new_obstacles"]] | _near(erase, d["new_obstacles"], 3))
    assert np.all(block[d["walls_gone"]])
    touched = {names[i] for i in np.unique(owner[erase | block])}
    changed = {k for k, a in d["areas"].items() if a["changed_m2"] > 0}
    assert changed and changed <= touched
    assert d["endpoint_share_on_walls"] < base["endpoint_share_on_walls"]


def _hit_cells(occ, runs, mount):
    from pipeline.update.map_patch import scans_with_poses

    poses, ranges, a0, da, rmax = scans_with_poses(runs, mount)
    ang = a0 + da * np.arange(ranges.shape[1])
    ok = np.isfinite(ranges) & (ranges < rmax)
    r, c = occ.world_to_cell((poses[:, :1] + ranges * np.cos(poses[:, 2:] + ang))[ok],
                             (poses[:, 1:2] + ranges * np.sin(poses[:, 2:] + ang))[ok])
    inside = occ.contains(r, c)
    out = np.zeros(occ.grid.shape, dtype=bool)
    out[r[inside], c[inside]] = True
    return out


def _seen_free(occ, runs, cfg, mount):
    from pipeline.update.map_patch import patch_map

    p = patch_map(occ, runs, mount, np.ones(occ.grid.shape, bool), cfg.update.mapping, progress=False)
    return p.observed & (p.occ_map.grid == FREE) & (occ.grid == FREE)


def _near(mask, cells, n):
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=n)[cells]


def test_new_data_of_another_frame_is_refused_and_nothing_is_written(micro_bundle, tmp_path):
    import yaml

    cfg, ing, _, _, bundle = micro_bundle
    other = tmp_path / "other"
    shutil.copytree(ing, other)
    doc = yaml.safe_load((other / "map.yaml").read_text())
    doc["origin"][0] += 1.0
    (other / "map.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match="map"):
        run_check(cfg, inputs={"bundle": bundle, "data": other}, outputs={"out": tmp_path / "c"}, localize=False,
                  progress=False)
    assert not (tmp_path / "c").exists()
    res = CliRunner().invoke(app, ["check", str(bundle), str(other), "--out", str(tmp_path / "c"), "--config", "ci",
                                   "--no-localize"])
    assert res.exit_code == 1 and "map.yaml" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "c").exists()
