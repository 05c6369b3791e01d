"""`synth --change --move-wall`: an interior wall of the changed building moves, and its map and laser world with it.

Pure scene tests (no rendering) on the micro site, whose movable walls are a room's side along a corridor, and on the
office preset, whose are partitions between rooms; one end-to-end synth checks the report and the map written.
"""

from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
import pytest
from scipy.ndimage import label

from pipeline.io.map_yaml import FREE, OCCUPIED, read_map
from pipeline.sitegen.change import ChangeSpec
from pipeline.sitegen.laser import LaserScanner, laser_world_grid, rasterise_map
from pipeline.sitegen.presets import load_site_preset
from pipeline.sitegen.render import egl_available
from pipeline.sitegen.synth import build_scene
from pipeline.sitegen.wall_move import choose_wall_move
from tests.sitegen.micro import captures, micro, synth

RES = 0.05
# Only the wall moves: the rest of the change (furniture, posters, plants, boards) is off, so the map's changes are
# the wall's and what it pushed.
ONLY_WALL = ChangeSpec(move_wall_m=0.5, move_share=0.0, poster_replace_share=0.0, poster_remove_share=0.0,
                       plant_remove_share=0.0, board_update_share=0.0)
CASES = [("micro", 3), ("micro", 2), ("office", 0)]  # micro 2: a wall with a doorway; office 0: between rooms


def _preset(name):
    return micro() if name == "micro" else load_site_preset(name, {})


def _scenes(name, seed, spec=ONLY_WALL, areas=()):
    base = build_scene(_preset(name), seed, False)
    return base, build_scene(_preset(name), seed, spec, areas), choose_wall_move(base, seed, spec.move_wall_m, areas)


def _line(wall):
    """(orientation, line, span start, span end) of an axis-aligned wall."""
    if abs(wall.y1 - wall.y0) < 1e-9:
        return "h", wall.y0, min(wall.x0, wall.x1), max(wall.x0, wall.x1)
    assert abs(wall.x1 - wall.x0) < 1e-9
    return "v", wall.x0, min(wall.y0, wall.y1), max(wall.y0, wall.y1)


def _cells(occ):
    xs = occ.origin_x + (np.arange(occ.width) + 0.5) * occ.resolution
    ys = occ.origin_y + (np.arange(occ.height) + 0.5) * occ.resolution
    return np.meshgrid(xs, ys)


def _slab(occ, orient, line, a0, a1, half):
    """Cells whose centres lie within `half` of the line between a0 and a1 along it (drawn here, not by the site)."""
    x, y = _cells(occ)
    across, along = (y, x) if orient == "h" else (x, y)
    return (np.abs(across - line) <= half) & (along >= a0) & (along <= a1)


def _footprint_mask(occ, o, grow):
    x, y = _cells(occ)
    c, s = math.cos(o.yaw + math.pi / 2), math.sin(o.yaw + math.pi / 2)
    u, v = c * (x - o.x) + s * (y - o.y), -s * (x - o.x) + c * (y - o.y)
    return (np.abs(u) <= o.size[0] / 2 + grow) & (np.abs(v) <= o.size[1] / 2 + grow)


@pytest.mark.parametrize(("name", "seed"), CASES)
def test_an_interior_wall_moves_by_the_distance_and_its_rooms_with_it(name, seed):
    base, changed, move = _scenes(name, seed)
    old, new = base.walls[move.wall], changed.walls[move.wall]
    assert not old.exterior and move.into and move.grows  # a partition: rooms (or a corridor) on both sides
    (o1, c1, a0, a1), (o2, c2, b0, b1) = _line(old), _line(new)
    assert o1 == o2 and (a0, a1) == (b0, b1) and abs(abs(c2 - c1) - 0.5) < 1e-9
    assert new.openings == old.openings and (new.thickness, new.height) == (old.thickness, old.height)
    assert move.before == (old.x0, old.y0, old.x1, old.y1) and move.after == (new.x0, new.y0, new.x1, new.y1)
    # Every other wall is the same, but for an end that lay on the old line and now lies on the new one.
    for w0, w1 in zip(base.walls, changed.walls, strict=True):
        if w0 is old or w0 == w1:
            continue
        ends0, ends1 = {(w0.x0, w0.y0), (w0.x1, w0.y1)}, {(w1.x0, w1.y0), (w1.x1, w1.y1)}
        (p0,), (p1,) = ends0 - ends1, ends1 - ends0
        k = 1 if o1 == "h" else 0
        assert abs(p0[k] - c1) < 1e-9 and abs(p1[k] - c2) < 1e-9 and p0[1 - k] == p1[1 - k]
    rooms0, rooms1 = {r.name: r for r in base.rooms}, {r.name: r for r in changed.rooms}
    depth = (lambda r: r.h) if o1 == "h" else (lambda r: r.w)
    for n in rooms0:
        r0, r1 = rooms0[n].rect, rooms1[n].rect
        grown = depth(r1) - depth(r0)
        assert math.isclose(grown, -0.5 if n in move.into else 0.5 if n in move.grows else 0.0, abs_tol=1e-9)
        assert math.isclose(sum(a.w * a.h for _, a in rooms1[n].areas), r1.w * r1.h)  # its areas still tile it


@pytest.mark.parametrize(("name", "seed"), CASES)
def test_the_map_changes_only_around_the_old_and_new_wall_and_every_door_still_connects(name, seed):
    base, changed, move = _scenes(name, seed)
    m0, m1 = rasterise_map(base, RES), rasterise_map(changed, RES)
    assert (m0.origin_x, m0.origin_y, m0.grid.shape) == (m1.origin_x, m1.origin_y, m1.grid.shape)
    wall = base.walls[move.wall]
    orient, c, a0, a1 = _line(wall)
    c2, t = _line(changed.walls[move.wall])[1], wall.thickness
    # The band around both positions (and what lies between), plus where pushed furniture stood and stands.
    band = _slab(m0, orient, (c + c2) / 2, a0 - t / 2 - RES, a1 + t / 2 + RES, abs(c2 - c) / 2 + t / 2 + RES)
    before = Counter((o.kind, o.x, o.y) for o in base.objects)
    after = Counter((o.kind, o.x, o.y) for o in changed.objects)
    moved = [o for o in base.objects if (before - after)[(o.kind, o.x, o.y)]] + \
            [o for o in changed.objects if (after - before)[(o.kind, o.x, o.y)]]
    allowed = band.copy()
    for o in moved:
        allowed |= _footprint_mask(m0, o, RES)
    diff = m0.grid != m1.grid
    assert diff.any() and not (diff & ~allowed).any()
    # The new wall stands where it should (but in its doorways) and the old one is gone (but where things now are).
    def solid(line):
        mask = _slab(m0, orient, line, a0 + t, a1 - t, t / 2 - RES)
        for o in wall.openings:
            lo, hi = sorted((wall.x0 + wall.direction[0] * o.start, wall.x0 + wall.direction[0] * o.end)
                            if orient == "h" else (wall.y0 + wall.direction[1] * o.start,
                                                   wall.y0 + wall.direction[1] * o.end))
            mask &= ~_slab(m0, orient, line, lo - RES, hi + RES, 1.0)
        return mask
    assert np.all(m1.grid[solid(c2)] == OCCUPIED) and np.all(m0.grid[solid(c)] == OCCUPIED)
    gone = solid(c)
    for o in changed.objects:
        if o.blocks_laser:
            gone &= ~_footprint_mask(m0, o, RES)
    assert gone.sum() > 0.5 * solid(c).sum() and np.all(m1.grid[gone] == FREE)
    # Doors: the rooms that free space connects to the corridors are the same, and each doorway joins its two sides.
    assert _connected_rooms(base, m0) == _connected_rooms(changed, m1) == {r.name for r in base.rooms}
    labels, _ = label(m1.grid == FREE)
    for w in changed.walls:
        for o in w.openings:
            if o.kind != "doorway":
                continue
            mid, (dx, dy) = (o.start + o.end) / 2, w.direction
            x, y = w.x0 + dx * mid, w.y0 + dy * mid
            sides = [m1.world_to_cell(x - s * dy * (t / 2 + 0.3), y + s * dx * (t / 2 + 0.3)) for s in (1, -1)]
            ids = {int(labels[int(r), int(col)]) for r, col in sides}
            assert len(ids) == 1 and 0 not in ids, (w, o)


def _connected_rooms(scene, occ) -> set[str]:
    """Rooms whose free space is in the corridors' connected part of the map."""
    labels, _ = label(occ.grid == FREE)
    x, y = _cells(occ)
    main = {}
    for room in scene.rooms:
        ids = labels[room.rect.contains(x, y, margin=0.3) & (labels > 0)]
        main[room.name] = Counter(ids.tolist()).most_common(1)[0][0] if ids.size else 0
    corridor = Counter(v for n, v in main.items() if n.startswith("corridor")).most_common(1)[0][0]
    return {n for n, v in main.items() if v == corridor}


def test_the_laser_world_has_the_wall_where_it_moved():
    base, changed, move = _scenes("micro", 3)
    wall = base.walls[move.wall]
    orient, c, a0, a1 = _line(wall)
    c2, t = _line(changed.walls[move.wall])[1], wall.thickness
    towards = math.copysign(1.0, c2 - c)
    stand, mid = c - towards * (t / 2 + 0.8), (a0 + a1) / 2  # 0.8 m before the old wall, in the room that grows
    heading = math.atan2(0.0, towards) if orient == "v" else math.atan2(towards, 0.0)
    pose = np.array([[stand, mid, heading] if orient == "v" else [mid, stand, heading]])
    ranges = []
    for scene in (base, changed):
        scanner = LaserScanner(laser_world_grid(scene, RES), beams=3, fov_deg=2.0, noise_sigma=0.0, dropout=0.0)
        ranges.append(float(scanner.cast_many(pose)[0, 1]))
    assert abs(ranges[0] - 0.8) < RES + 1e-3 and abs(ranges[1] - 1.3) < RES + 1e-3


def test_the_same_seed_moves_the_same_wall_and_seeds_pick_among_several():
    preset = micro()
    a, b = (build_scene(preset, 3, ChangeSpec(move_wall_m=0.5)) for _ in range(2))
    assert repr(a) == repr(b)
    walls = {choose_wall_move(build_scene(preset, s, False), s, 0.5).before for s in range(6)}
    assert len(walls) > 1


def test_without_move_wall_the_change_keeps_every_wall_and_room():
    base = build_scene(micro(), 3, False)
    changed = build_scene(micro(), 3, True)
    assert changed.walls == base.walls and changed.rooms == base.rooms and changed.lights == base.lights
    assert repr(build_scene(micro(), 3, ChangeSpec())) == repr(changed)


def test_with_areas_the_wall_bounds_a_selected_room():
    base = build_scene(micro(), 3, False)
    chosen = 0
    for room in base.rooms:
        for areas in ((room.name,), (f"{room.name}/{room.areas[-1][0]}",)):
            move = choose_wall_move(base, 3, 0.5, areas)
            if move is None:
                with pytest.raises(ValueError, match="no interior wall"):
                    build_scene(micro(), 3, ChangeSpec(move_wall_m=0.5), areas)
                continue
            chosen += 1
            assert room.name in move.rooms
            changed = build_scene(micro(), 3, ChangeSpec(move_wall_m=0.5), areas)
            assert changed.walls[move.wall] != base.walls[move.wall]
            assert sum(w0 != w1 for w0, w1 in zip(base.walls, changed.walls, strict=True)) >= 1
    assert chosen >= 8  # most rooms have a wall that may move
    with pytest.raises(ValueError, match="no interior wall"):
        build_scene(micro(), 3, ChangeSpec(move_wall_m=3.0))  # no room is that deep


@pytest.mark.skipif(not egl_available(), reason="no headless EGL context on this machine")
def test_synth_writes_the_moved_wall_into_its_map_and_report_and_moves_the_stop_it_crowds(tmp_path):
    base = build_scene(micro(), 1, False)
    room = choose_wall_move(base, 1, 0.5).into[0]  # seed 1: the wall comes to stand where the room's stop was
    site = synth(tmp_path / "moved", seed=1, change_areas=(room,), areas=(room,), move_wall_m=0.5, workers=1)
    report = json.loads((site / "synth_report.json").read_text())
    move = choose_wall_move(base, 1, 0.5, (room,))
    moved = report["wall_moved"]
    assert {k: moved[k] for k in ("rooms", "into", "grows", "from", "to", "distance_m")} == move.record()
    assert room in moved["rooms"] and moved["distance_m"] == 0.5
    changed = build_scene(micro(), 1, ChangeSpec(move_wall_m=0.5), (room,))
    occ = read_map(site / "map.yaml")
    assert np.array_equal(occ.grid, rasterise_map(changed, micro().map_resolution).grid)
    # The room's stop, which the wall now crowds, is captured where its room has room, under its own id.
    rows = captures(site)
    assert rows and {r["room"] for r in rows} == {room} and not moved["stops_not_captured"]
    assert set(moved["stops_moved"]) == {r["stop_id"] for r in rows}
    for r in rows:
        (x0, y0), (x1, y1) = moved["stops_moved"][r["stop_id"]]
        assert (float(r["x"]), float(r["y"])) == (round(x1, 4), round(y1, 4)) != (round(x0, 4), round(y0, 4))
        assert occ.value_at(np.array([x1]), np.array([y1]))[0] == FREE
        assert next(q for q in changed.rooms if q.name == room).rect.contains(x1, y1, margin=micro().stops.clearance)
