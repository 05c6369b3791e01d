"""`update`: new captures replace the stops of their areas, the rest stays byte-identical, the map is patched
only inside the changed areas, the changelog says exactly what changed, and bad inputs write nothing."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from typer.testing import CliRunner

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.ingest import run_ingest
from pipeline.io.map_yaml import OCCUPIED, read_map
from pipeline.update.site_update import run_update
from tests.fixtures.capture_site import RES, STOPS, floor_map, write_capture_site

CFG = load_config("ci")
ROOM_B = [s for s in STOPS if s[4] == "room_b"]
BLOCK = (slice(int(2.8 / RES), int(3.2 / RES)), slice(int(3.6 / RES), int(4.0 / RES)))  # rows (y), cols (x)


def _ingest(site, out):
    return run_ingest(CFG, inputs={"site": site}, outputs={"out": out}, progress=False)


def changed_floor():
    """The floor with a cabinet (40 x 40 cm) in room_b, beside its north-east stop."""
    occ = floor_map()
    occ.grid[BLOCK] = OCCUPIED
    return occ


@pytest.fixture(scope="module")
def sites(tmp_path_factory):
    root = tmp_path_factory.mktemp("upd")
    old = _ingest(write_capture_site(root / "site"), root / "old")
    recapture = write_capture_site(root / "site_b", stops=ROOM_B, occ=changed_floor(), shade=90)
    new = _ingest(recapture, root / "new")
    return root, old, new


@pytest.fixture(scope="module")
def updated(sites):
    root, old, new = sites
    return run_update(CFG, inputs={"site_db": old, "new_data": new}, outputs={"out": root / "v2"}, progress=False)


def _rows(path, stops=None):
    rows = pq.read_table(path).to_pylist()
    return [r for r in rows if stops is None or r["stop_id"] in stops]


def test_untouched_stops_keep_their_rows_boxes_and_files_byte_identical(sites, updated):
    _, old, new = sites
    kept = {"s0", "s1"}
    assert _rows(updated / "images.parquet", kept) == _rows(old / "images.parquet", kept)
    ids = {r["image_id"] for r in _rows(old / "images.parquet", kept)}
    old_boxes = [b for b in pq.read_table(old / "boxes.parquet").to_pylist() if b["image_id"] in ids]
    new_boxes = [b for b in pq.read_table(updated / "boxes.parquet").to_pylist() if b["image_id"] in ids]
    assert new_boxes == old_boxes and old_boxes
    for i in ids:
        assert (updated / i).read_bytes() == (old / i).read_bytes()


def test_a_replaced_stops_old_rows_are_gone_and_the_new_ones_are_in(sites, updated):
    _, old, new = sites
    got = _rows(updated / "images.parquet", {"s2", "s3"})
    assert got == _rows(new / "images.parquet")
    old_sha = {r["sha256"] for r in _rows(old / "images.parquet", {"s2", "s3"})}
    assert not old_sha & {r["sha256"] for r in _rows(updated / "images.parquet")}
    for r in got:
        assert (updated / r["image_id"]).read_bytes() == (new / r["image_id"]).read_bytes()
    assert pq.read_table(updated / "images.parquet").num_rows == 4 * 6


def test_the_map_changes_only_inside_the_changed_areas_and_gains_the_cabinet(sites, updated):
    _, old, _ = sites
    before, after = read_map(old / "map.yaml"), read_map(updated / "map.yaml")
    x = (np.arange(before.width) + 0.5) * RES  # cell centres; the wall between the rooms spans x 2.95-3.05 m
    changed = before.grid != after.grid
    assert changed.any() and (np.broadcast_to(x, changed.shape)[changed] > 3.0).all()  # room_b's side only
    cabinet = after.grid[BLOCK]
    # The cabinet's faces that the run saw are occupied now (its inside is never observed).
    assert (cabinet == OCCUPIED).sum() >= 8 and (before.grid[BLOCK] != OCCUPIED).all()
    room_a = x < 3.0
    assert np.array_equal(before.grid[:, room_a], after.grid[:, room_a])


def test_the_changelog_lists_what_changed_and_nothing_else(sites, updated):
    c = json.loads((updated / "changelog.json").read_text())
    assert c["changed_areas"] == ["room_b/east", "room_b/west"]
    assert c["areas"] == {
        "room_b/east": {**c["areas"]["room_b/east"], "stops_removed": ["s3"], "stops_added": ["s3"],
                        "images_removed": 6, "images_added": 6},
        "room_b/west": {**c["areas"]["room_b/west"], "stops_removed": ["s2"], "stops_added": ["s2"],
                        "images_removed": 6, "images_added": 6},
    }
    before, after = read_map(sites[1] / "map.yaml"), read_map(updated / "map.yaml")
    assert c["map"]["cells_changed"] == int((before.grid != after.grid).sum())
    assert sum(a["map_cells_changed"] for a in c["areas"].values()) == c["map"]["cells_changed"]
    assert c["runs"] == {"added": [], "replaced": ["query_a"], "removed": [], "kept": []}
    assert c["totals"]["stops_kept"] == 2 and c["totals"]["images_kept"] == 12
    assert (updated / "map_patch.png").is_file() and "room_b/west" in (updated / "changelog.md").read_text()


def test_an_unlabelled_capture_replaces_the_area_of_the_nearest_old_stop(sites, tmp_path):
    _, old, _ = sites
    stop = ("n1", 4.1, 1.05, 1.5, "", "")
    new = _ingest(write_capture_site(tmp_path / "s", stops=[stop], with_run=False), tmp_path / "new")
    out = run_update(CFG, inputs={"site_db": old, "new_data": new}, outputs={"out": tmp_path / "v2"},
                     progress=False)
    rows = _rows(out / "images.parquet")
    assert {r["stop_id"] for r in rows} == {"s0", "s1", "s3", "n1"}
    assert {(r["room"], r["area"]) for r in rows if r["stop_id"] == "n1"} == {("room_b", "west")}
    c = json.loads((out / "changelog.json").read_text())
    assert c["changed_areas"] == ["room_b/west"] and c["map"]["scans_used"] == 0
    assert read_map(out / "map.yaml").grid.tobytes() == read_map(old / "map.yaml").grid.tobytes()


def test_stops_and_runs_can_be_removed_explicitly(sites, tmp_path):
    _, old, new = sites
    out = run_update(CFG, inputs={"site_db": old, "new_data": new}, outputs={"out": tmp_path / "v2"},
                     remove_stops=["s0"], progress=False)
    assert {r["stop_id"] for r in _rows(out / "images.parquet")} == {"s1", "s2", "s3"}
    c = json.loads((out / "changelog.json").read_text())
    assert c["areas"]["room_a/west"]["stops_removed"] == ["s0"] and c["stops_removed_explicitly"] == ["s0"]
    assert c["areas"]["room_a/west"]["stops_added"] == []


def _break_camera(site):
    y = yaml.safe_load((site / "site.yaml").read_text())
    y["camera"]["fx"] = 55.0
    (site / "site.yaml").write_text(yaml.safe_dump(y))


def _break_frame(site):
    y = yaml.safe_load((site / "map.yaml").read_text())
    y["origin"] = [1.0, 0.0, 0.0]
    (site / "map.yaml").write_text(yaml.safe_dump(y))


def _break_area(site):
    from pipeline.io import tables

    t = tables.read_table(site / "images.parquet", "images")
    t = t.set_column(t.schema.get_field_index("area"), t.schema.field("area"), [["basement"] * t.num_rows])
    tables.write_table(site / "images.parquet", t, "images")


@pytest.mark.parametrize(("breaker", "words"), [
    (_break_camera, ["camera differs", "same sensors"]),
    (_break_frame, ["map frame", "origin"]),
    (_break_area, ["area 'room_b/basement'", "does not have", "room_b/east, room_b/west"]),
    (None, ["--remove-stop 'nope'"]),
])
def test_bad_inputs_are_refused_with_the_fix_and_nothing_is_written(sites, tmp_path, breaker, words):
    _, old, new = sites
    copy = tmp_path / "new"
    shutil.copytree(new, copy)
    if breaker is not None:
        breaker(copy)
    with pytest.raises(InputError) as err:
        run_update(CFG, inputs={"site_db": old, "new_data": copy}, outputs={"out": tmp_path / "v2"},
                   remove_stops=["nope"] if breaker is None else [], progress=False)
    text = str(err.value) + " ".join(str(p) for p in err.value.problems)
    assert all(w in text for w in words), text
    assert not (tmp_path / "v2").exists() and not list(tmp_path.glob(".v2*"))


def test_the_cli_prints_what_changed_and_refuses_bad_input_without_a_traceback(sites, tmp_path):
    from stages.app import app

    _, old, new = sites
    ok = CliRunner().invoke(app, ["update", str(old), str(new), "--out", str(tmp_path / "v2"), "--config", "ci"])
    assert ok.exit_code == 0, ok.output
    assert "areas changed: room_b/east, room_b/west" in ok.output and "kept 2 stops" in ok.output
    bad = CliRunner().invoke(app, ["update", str(old), str(tmp_path / "missing"), "--out", str(tmp_path / "v3"),
                                   "--config", "ci"])
    assert bad.exit_code == 1 and "Traceback" not in bad.output and "missing" in bad.output
