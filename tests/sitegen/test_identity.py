"""Identity cues: plates, pictures, signage, wings; deterministic, distinct, true to the floor, off the laser."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from pipeline.sitegen import pictures, signage
from pipeline.sitegen.change import change_scene
from pipeline.sitegen.decals import SiteTextures
from pipeline.sitegen.furnish import furnish_scene
from pipeline.sitegen.identity import SIGNAGE_KINDS, _grid
from pipeline.sitegen.laser import rasterise_map
from pipeline.sitegen.layout import generate_plan
from pipeline.sitegen.presets import load_site_preset

PHOTO = np.random.default_rng(0).integers(0, 256, (300, 400, 3), dtype=np.uint8)


def scene_of(name: str, seed: int = 0, overrides: dict | None = None):
    preset = load_site_preset(name, overrides)
    return furnish_scene(generate_plan(preset, seed), preset, seed)


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def all_textures(scene, unique: bool = True) -> dict[int, str]:
    tex = SiteTextures(scene, [PHOTO], unique)
    out = {}
    for o in scene.objects:
        if o.kind in SIGNAGE_KINDS:
            out[o.instance_id] = digest(tex.signage(o))
        elif o.cls == "poster":
            out[o.instance_id] = digest(tex.poster(o.texture))
    return out


@pytest.fixture(scope="module")
def office():
    return scene_of("office")


def test_same_seed_same_cues_and_bytes(office):
    again = scene_of("office")
    assert office.objects == again.objects and office.wings == again.wings and office.paint == again.paint
    assert all_textures(office) == all_textures(again)
    assert digest(pictures.picture(7, 3, [PHOTO])) == digest(pictures.picture(7, 3, [PHOTO]))
    assert digest(pictures.picture(7, 3, [PHOTO])) != digest(pictures.picture(7, 4, [PHOTO]))
    assert scene_of("office", 1).objects != office.objects


def test_every_room_has_one_plate_by_its_door_and_no_number_repeats(office):
    rooms = {r.name: r for r in office.rooms if r.kind != "corridor"}
    plates = [o for o in office.objects if o.kind == "plate"]
    numbers = [o.label.split("|")[0] for o in plates]
    assert len(numbers) == len(set(numbers)) == len(rooms)
    assert sorted(o.room for o in plates) == sorted(rooms)
    doors = {o.room: o for o in office.objects if o.kind == "door" and o.room in rooms and o.size[1] < 0.06}
    for o in plates:
        # On the corridor side of the wall, facing the corridor, within a metre of the room's doorway.
        ahead = office.room_at(o.x + 0.4 * math.cos(o.yaw), o.y + 0.4 * math.sin(o.yaw))[0]
        assert ahead.startswith("corridor"), (o.label, ahead)
        behind = office.room_at(o.x - 0.4 * math.cos(o.yaw), o.y - 0.4 * math.sin(o.yaw))[0]
        assert behind == o.room
        assert math.hypot(o.x - doors[o.room].x, o.y - doors[o.room].y) < 1.6
        assert not o.blocks_laser and 1.2 < o.z < 1.8


def test_no_picture_repeats_in_office_and_twins_repeats(office):
    posters = [o for o in office.objects if o.cls == "poster"]
    assert len(posters) > 20
    assert len({o.texture for o in posters}) == len(posters)
    tex = all_textures(office)
    assert len({tex[o.instance_id] for o in posters}) == len(posters)  # the images themselves differ
    twins = scene_of("twins")
    t_posters = [o for o in twins.objects if o.cls == "poster"]
    assert len({o.texture for o in t_posters}) <= load_site_preset("twins").furnishing.poster_pictures < len(t_posters)
    assert not twins.wings and not [o for o in twins.objects if o.kind in SIGNAGE_KINDS]


def test_cues_are_off_the_laser_plane_and_leave_the_map_unchanged(office):
    cues = [o for o in office.objects if o.kind in (*SIGNAGE_KINDS, "clutter")]
    assert {o.kind for o in cues} == {*SIGNAGE_KINDS, "clutter"}
    assert not any(o.blocks_laser for o in cues)
    stripped = scene_of("office")
    stripped.objects = [o for o in stripped.objects if o.kind not in (*SIGNAGE_KINDS, "clutter")]
    assert np.array_equal(rasterise_map(office, 0.1).grid, rasterise_map(stripped, 0.1).grid)


def test_wings_partition_the_floor_and_corridors_wear_their_colour(office):
    assert [w.letter for w in office.wings] == ["A", "B", "C", "D"]
    assert len({w.colour for w in office.wings}) == 4
    area = sum(w.rect.w * w.rect.h for w in office.wings)
    assert area == pytest.approx(office.bounds.w * office.bounds.h)
    assert _grid(4, 40 / 30) == (2, 2) and _grid(6, 1.0) in ((2, 3), (3, 2)) and _grid(2, 3.0) == (2, 1)
    from pipeline.sitegen.identity import surface_at

    for w in office.wings:
        for c in (r.rect for r in office.rooms if r.kind == "corridor"):
            x0, x1, y0, y1 = max(c.x0, w.rect.x0), min(c.x1, w.rect.x1), max(c.y0, w.rect.y0), min(c.y1, w.rect.y1)
            if x1 - x0 > 0.5 and y1 - y0 > 0.5:  # a piece of corridor inside this wing
                _, tint = surface_at(office, (x0 + x1) / 2, (y0 + y1) / 2, 5)
                assert np.allclose(tint, 0.3 + 0.7 * np.asarray(w.colour))


def test_escape_plan_marks_where_it_hangs(office):
    plan = next(o for o in office.objects if o.kind == "escape_plan")
    img = signage.plan_image(office, (plan.x, plan.y), plan.yaw).astype(int)
    red = (img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)
    ys, xs = np.nonzero(red)
    h, w = signage.PLAN_PX
    b = office.bounds
    scale = min((w - 16) / b.w, (h - 36) / b.h)
    ox, oy = (w - b.w * scale) / 2, 28 + (h - 32 - b.h * scale) / 2
    # Inverting the plan's projection by hand: the dot's centre is where the plan hangs, within a pixel.
    here_x, here_y = b.x0 + (np.median(xs) - ox) / scale, b.y1 - (np.median(ys) - oy) / scale
    assert math.hypot(here_x - plan.x, here_y - plan.y) < 1.5 / scale


def test_signs_name_the_wings_either_way(office):
    from pipeline.sitegen.identity import cue_label

    a, b = office.wings[0], office.wings[1]  # side by side along x
    y = a.rect.cy
    label = cue_label(office, "sign", a.rect.x1, y, -math.pi / 2, 0)  # on a wall facing south (-y)
    # Facing the sign (looking north), west (wing A) is on the left and east (wing B) on the right.
    assert label == f"sign:Wing {a.letter} <:Wing {b.letter} >"


def test_change_replaces_pictures_and_notes_but_keeps_plates(office):
    changed = change_scene(office, 0, unique_pictures=True)
    assert [o.label for o in changed.objects if o.kind == "plate"] == [o.label for o in office.objects
                                                                       if o.kind == "plate"]
    before = {o.texture for o in office.objects if o.cls == "poster"}
    after = [o.texture for o in changed.objects if o.cls == "poster"]
    new = [t for t in after if t not in before]
    assert new and len(set(after)) == len(after)  # new pictures, never seen on this floor, still unique
    boards = [o.label for o in changed.objects if o.kind == "notice_board"]
    assert any(label.endswith(":v1") for label in boards)


def test_picture_styles_differ_and_have_the_stated_shape():
    pool = [pictures.picture(i, 0, [PHOTO]) for i in range(2 * len(pictures.STYLES))]
    assert len({digest(p) for p in pool}) == len(pool)
    assert all(p.dtype == np.uint8 and p.shape[2] == 3 and sorted(p.shape[:2]) == sorted(pictures.SIZE) for p in pool)
    assert not np.array_equal(pictures.picture(0, 0, []), pictures.picture(0, 0, [PHOTO]))  # no photo: drawn


def test_painted_corridors_wear_a_dado_of_their_wing_colour_and_rooms_their_paint(office):
    from pipeline.sitegen.identity import PAINT, surface_at, surface_bands

    assert office.painted and office.dado_height == pytest.approx(1.0)
    corridors = [r.rect for r in office.rooms if r.kind == "corridor"]
    for w in office.wings:
        c = next(c for c in corridors if min(c.x1, w.rect.x1) - max(c.x0, w.rect.x0) > 1
                 and min(c.y1, w.rect.y1) - max(c.y0, w.rect.y0) > 1)  # a piece of corridor inside this wing
        x, y = (max(c.x0, w.rect.x0) + min(c.x1, w.rect.x1)) / 2, (max(c.y0, w.rect.y0) + min(c.y1, w.rect.y1)) / 2
        bands = surface_bands(office, x, y, 5)
        assert [b[0] for b in bands] == [1.0, 1.04, math.inf] and {b[1] for b in bands} == {PAINT}
        assert np.allclose(bands[0][2], 0.15 + 0.8 * np.asarray(w.colour))  # the dado: the wing's colour
        assert min(bands[2][2]) > 0.8  # above it: light paint
    for room in (r for r in office.rooms if r.kind != "corridor"):
        assert surface_bands(office, room.rect.cx, room.rect.cy, 5) == [(math.inf, PAINT, office.paint[room.name])]
    twins = scene_of("twins")  # unpainted: one band, the library's texture as before
    x, y = twins.rooms[0].rect.cx, twins.rooms[0].rect.cy
    assert not twins.painted and surface_bands(twins, x, y, 5) == [(math.inf, *surface_at(twins, x, y, 5))]


def test_paint_is_smooth_and_deterministic():
    from pipeline.sitegen.identity import paint_texture

    a = paint_texture()
    assert a.shape == (128, 128, 3) and a.dtype == np.uint8 and np.array_equal(a, paint_texture())
    assert 225 < a.mean() < 245 and a.std() < 5  # near-white matt paint, a faint mottle, no grain


def test_painted_walls_cover_the_same_surface_cut_at_the_dado(office):
    from pipeline.sitegen.geometry import structure_meshes
    from pipeline.sitegen.identity import paint_texture

    class Library:  # flat textures: only the geometry and the paint are under test
        textures = {"wall": [np.full((4, 4, 3), 200, np.uint8)] * 5, "floor": [np.zeros((4, 4, 3), np.uint8)] * 3,
                    "ceiling": [np.zeros((4, 4, 3), np.uint8)]}

    def walls(scene):  # the meshes wearing a wall texture or the paint
        return [m for m in structure_meshes(scene, Library) if m.texture is Library.textures["wall"][0]
                or m.texture.shape[0] == 128]

    def area(meshes):
        total = 0.0
        for m in meshes:
            t = m.positions.reshape(-1, 3, 3)
            total += 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
        return total

    plain = scene_of("office")
    plain.painted, plain.dado_height = False, 0.0
    painted_walls, plain_walls = walls(office), walls(plain)
    assert area(painted_walls) == pytest.approx(area(plain_walls), rel=1e-6)  # the same walls, only cut and painted
    paint = [m for m in painted_walls if m.texture.shape[0] == 128]
    assert paint and all(np.array_equal(m.texture, paint_texture()) for m in paint)
    dado_colours = {tuple(float(v) for v in 0.15 + 0.8 * np.asarray(w.colour)) for w in office.wings}
    dados = [m for m in paint if tuple(m.colour) in dado_colours]
    assert dados and max(m.positions[:, 2].max() for m in dados) <= office.dado_height + 1e-6


def test_every_office_and_meeting_room_has_a_pinboard_of_its_own(office):
    from pipeline.sitegen.identity import ROOM_BOARD_Z

    rooms = [r.name for r in office.rooms if r.kind in ("office", "meeting")]
    boards = [o for o in office.objects if o.kind == "notice_board" and not o.room.startswith("corridor")]
    assert sorted(o.room for o in boards) == sorted(rooms)
    assert all(o.z == ROOM_BOARD_Z and not o.blocks_laser for o in boards)
    labels = [o.label for o in office.objects if o.kind == "notice_board"]
    assert len(set(labels)) == len(labels)  # no two boards of the floor show the same notes
    assert not [o for o in scene_of("twins").objects if o.kind == "notice_board"]


def test_painted_walls_alone_paint_a_floor_without_wings_white():
    from pipeline.sitegen.geometry import structure_meshes
    from pipeline.sitegen.identity import PAINT, surface_bands

    plain = scene_of("twins", overrides={"identity.painted_walls": True})
    assert plain.painted and not plain.wings and not plain.paint
    for room in plain.rooms:
        assert surface_bands(plain, room.rect.cx, room.rect.cy, 5) == [(math.inf, PAINT, (1.0, 1.0, 1.0))]

    class Library:
        textures = {"wall": [np.full((4, 4, 3), 200, np.uint8)] * 5, "floor": [np.zeros((4, 4, 3), np.uint8)] * 3,
                    "ceiling": [np.zeros((4, 4, 3), np.uint8)]}

    walls = [m for m in structure_meshes(plain, Library) if m.texture.shape[0] == 128]
    assert len(walls) == 1 and walls[0].colour == (1.0, 1.0, 1.0)  # one white paint, no library texture left
    assert not [m for m in structure_meshes(plain, Library) if m.texture is Library.textures["wall"][0]]
