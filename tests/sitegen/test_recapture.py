"""`synth --area` / `--change-area`: a change confined to some rooms, and a re-capture of just those rooms that
`update` merges into the unchanged site's database."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import astuple, replace

import pytest

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.ingest import run_ingest
from pipeline.sitegen.render import egl_available
from pipeline.sitegen.synth import build_scene
from pipeline.update.site_update import run_update
from tests.sitegen.micro import captures, micro, synth

pytestmark = pytest.mark.skipif(not egl_available(), reason="no headless EGL context on this machine")


def _busiest_room(site_dir):
    return Counter(r["room"] for r in captures(site_dir) if r["room"]).most_common(1)[0][0]


def _objects(scene):
    return [astuple(replace(o, instance_id=0)) for o in scene.objects]


def test_a_change_confined_to_a_room_leaves_every_other_object_as_it_was():
    from pipeline.sitegen.change import in_areas

    base = build_scene(micro(), 3, False)
    room = max(base.rooms, key=lambda r: sum(o.room == r.name for o in base.objects)).name
    changed = build_scene(micro(), 3, True, (room,))
    outside = [o for o in _objects(base) if not in_areas(base, o[3], o[4], (room,))]
    after_outside = [o for o in _objects(changed) if not in_areas(base, o[3], o[4], (room,))]
    assert outside == after_outside and len(outside) < len(_objects(base))
    inside_before = {o for o in _objects(base) if in_areas(base, o[3], o[4], (room,))}
    inside_after = {o for o in _objects(changed) if in_areas(base, o[3], o[4], (room,))}
    assert inside_before != inside_after
    with pytest.raises(ValueError, match="no area"):
        build_scene(micro(), 3, True, ("no_such_room",))


def test_a_recapture_of_a_changed_room_updates_the_sites_database(site, tmp_path):
    room = _busiest_room(site)
    sub = synth(tmp_path / "sub", areas=(room,), change_areas=(room,), workers=1)
    full_rows = [r for r in captures(site) if r["room"] == room]
    assert captures(sub) == full_rows  # the same stops, ids and poses: the building's capture plan
    report = json.loads((sub / "synth_report.json").read_text())
    assert report["stops"] == len(full_rows) // 6 < report["stops_of_the_site"]
    assert report["change_areas"] == [room] and report["areas"] == [room]
    differ = sum((sub / r["image"]).read_bytes() != (site / r["image"]).read_bytes() for r in full_rows)
    assert differ > 0

    cfg = load_config("ci")
    old = run_ingest(cfg, inputs={"site": site}, outputs={"out": tmp_path / "old"}, progress=False)
    new = run_ingest(cfg, inputs={"site": sub}, outputs={"out": tmp_path / "new"}, progress=False)
    v2 = run_update(cfg, inputs={"site_db": old, "new_data": new}, outputs={"out": tmp_path / "v2"}, progress=False)
    log = json.loads((v2 / "changelog.json").read_text())
    assert all(k == room or k.startswith(f"{room}/") for k in log["changed_areas"])
    assert sorted(s for a in log["areas"].values() for s in a["stops_added"]) == sorted(
        {r["stop_id"] for r in full_rows})
    others = [r for r in captures(site) if r["room"] != room]
    assert all((v2 / r["image"]).read_bytes() == (site / r["image"]).read_bytes() for r in others)


def test_an_area_the_site_does_not_have_is_refused_before_rendering(tmp_path):
    with pytest.raises(InputError, match="no such area"):
        synth(tmp_path / "x", areas=("no_such_room",))
    assert not (tmp_path / "x").exists()
