"""Floor plans and furnishing: deterministic, consistent geometry, every class present, loops and doors."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.sitegen.change import change_scene
from pipeline.sitegen.furnish import furnish_scene
from pipeline.sitegen.geometry import wall_pieces
from pipeline.sitegen.layout import generate_plan
from pipeline.sitegen.presets import load_site_preset


def scene_of(name: str, seed: int = 0):
    preset = load_site_preset(name)
    return furnish_scene(generate_plan(preset, seed), preset, seed)


@pytest.mark.parametrize("name", ["tiny", "office", "twins", "paper"])
def test_presets_build_and_every_class_is_present(name):
    scene = scene_of(name)
    counts = scene.class_counts()
    assert all(n > 0 for n in counts.values()), counts
    w, h = load_site_preset(name).floor.size
    assert (scene.bounds.w, scene.bounds.h) == (w, h)


def test_same_seed_same_scene_other_seed_other_scene():
    a, b, c = scene_of("office", 3), scene_of("office", 3), scene_of("office", 4)
    assert a.walls == b.walls and a.objects == b.objects and a.rooms == b.rooms
    assert a.objects != c.objects


def test_rooms_do_not_overlap_and_stay_inside():
    scene = scene_of("office")
    rooms = [r for r in scene.rooms if r.kind != "corridor"]
    for r in rooms:
        assert scene.bounds.x0 <= r.rect.x0 < r.rect.x1 <= scene.bounds.x1
    for a, b in itertools.combinations(rooms + [r for r in scene.rooms if r.kind == "corridor"], 2):
        ox = min(a.rect.x1, b.rect.x1) - max(a.rect.x0, b.rect.x0)
        oy = min(a.rect.y1, b.rect.y1) - max(a.rect.y0, b.rect.y0)
        assert not (ox > 1e-6 and oy > 1e-6) or (a.kind == b.kind == "corridor"), (a.name, b.name)


def test_every_room_has_one_doorway_on_a_corridor():
    scene = scene_of("office")
    doorways = [(w, o) for w in scene.walls for o in w.openings if o.kind == "doorway"]
    for room in (r for r in scene.rooms if r.kind != "corridor"):
        found = 0
        for w, o in doorways:
            dx, dy = w.direction
            mid = (o.start + o.end) / 2
            cx, cy = w.x0 + dx * mid, w.y0 + dy * mid
            sides = [scene.room_at(cx - dy * s * 0.3, cy + dx * s * 0.3)[0] for s in (1, -1)]
            if room.name in sides:
                assert any(s.startswith("corridor") for s in sides), room.name
                found += 1
        assert found == 1, (room.name, found)


def test_walls_are_merged_and_openings_fit():
    scene = scene_of("paper")
    keys = [(w.x0, w.y0, w.x1, w.y1) for w in scene.walls]
    assert len(keys) == len(set(keys))
    for w in scene.walls:
        for o in w.openings:
            assert 0 <= o.start < o.end <= w.length + 1e-6 and 0 <= o.z0 < o.z1 <= w.height


def test_wall_pieces_cover_the_wall_minus_its_openings():
    scene = scene_of("office")
    for w in scene.walls:
        solid = sum((a1 - a0) * (z1 - z0) for a0, a1, z0, z1 in wall_pieces(w))
        holes = sum((o.end - o.start) * (o.z1 - o.z0) for o in w.openings)
        assert math.isclose(solid, w.length * w.height - holes, rel_tol=1e-9, abs_tol=1e-9)


def test_corridors_form_loops():
    scene = scene_of("office")
    corridors = [r for r in scene.rooms if r.kind == "corridor"]
    horizontal = [r for r in corridors if r.name.startswith("corridor_h")]
    vertical = [r for r in corridors if r.name.startswith("corridor_v")]
    assert len(horizontal) >= 2 and len({r.rect.x0 for r in vertical}) >= 2  # two lines each way: a loop


def test_objects_sit_in_free_space_of_their_room():
    scene = scene_of("office")
    for o in scene.objects:
        if o.cls in ("chair", "trash_bin", "plant") and o.room and not o.room.startswith("corridor"):
            room = next(r for r in scene.rooms if r.name == o.room)
            assert room.rect.contains(o.x, o.y), (o.kind, o.room)


def test_change_moves_furniture_and_swaps_posters_but_keeps_walls():
    before = scene_of("office")
    after = change_scene(before, seed=0)
    assert after.walls == before.walls and after.name.endswith("-changed")
    chairs_before = np.array([(o.x, o.y) for o in before.objects if o.cls == "chair"])
    chairs_after = np.array([(o.x, o.y) for o in after.objects if o.cls == "chair"])
    assert len(chairs_after) == len(chairs_before)
    moved = np.linalg.norm(chairs_after - chairs_before, axis=1) > 0.1
    assert 0.2 < moved.mean() < 0.9
    posters_before = sorted(o.texture for o in before.objects if o.cls == "poster")
    posters_after = sorted(o.texture for o in after.objects if o.cls == "poster")
    assert posters_before != posters_after
    assert [o.instance_id for o in after.objects] == list(range(1, len(after.objects) + 1))
    # Posters (old and hung by the change) cover no door, window or other wall fixture.
    fixtures = [o for o in after.objects if o.kind in ("door", "door_exterior", "window", "exit_sign",
                                                         "fire_extinguisher")]
    for p in (o for o in after.objects if o.cls == "poster"):
        for f in fixtures:
            assert math.hypot(p.x - f.x, p.y - f.y) >= (p.size[0] + f.size[0]) / 2, (p, f)
    old_spots = {(round(o.x, 3), round(o.y, 3)) for o in before.objects if o.cls == "poster"}
    assert any((round(o.x, 3), round(o.y, 3)) not in old_spots for o in after.objects if o.cls == "poster")


def test_bad_preset_names_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("floor:\n  sise: [10, 10]\n")
    with pytest.raises(ConfigError, match="floor.sise"):
        load_site_preset(path)
    path.write_text("floor:\n  size: [10, 10]\n  corridors_x: 4\n")
    with pytest.raises(ConfigError, match=r"need .* m but the floor has 10.0 m: enlarge floor.size"):
        load_site_preset(path)
    with pytest.raises(ConfigError, match="unknown site preset 'castle'"):
        load_site_preset("castle")
