"""Objects of a reference site: doors, windows, desks and chairs, posters, extinguishers, bins, plants, exit signs.

Placement follows how offices are furnished, with the same few arrangements repeated from room to room
(which is what makes single images ambiguous): desks along the far wall with a chair each, meeting
tables ringed by chairs, posters on side walls and along corridors, extinguishers and exit signs at
regular spacing on corridor walls, an exit sign over every exterior door.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import numpy as np

from pipeline.sitegen import identity
from pipeline.sitegen.presets import SitePreset
from pipeline.sitegen.scene import Rect, Room, Scene, SceneObject

_NORMALS = {"north": math.pi / 2, "south": -math.pi / 2, "east": 0.0, "west": math.pi}
_SIZES = {
    "door": (0.95, 0.08, 2.05), "door_exterior": (1.6, 0.1, 2.1), "window": (1.2, 0.12, 1.2),
    "chair": (0.5, 0.52, 0.9), "desk": (1.4, 0.7, 0.75), "table": (1.8, 0.9, 0.75), "cabinet": (0.8, 0.45, 1.2),
    "poster": (0.6, 0.03, 0.85), "fire_extinguisher": (0.22, 0.18, 0.6), "trash_bin": (0.32, 0.32, 0.45),
    "plant": (0.5, 0.5, 1.2), "exit_sign": (0.36, 0.06, 0.16), **identity.SIZES,
}


class _Placer:
    def __init__(self, scene: Scene, preset: SitePreset, rng):
        self.scene, self.preset, self.rng = scene, preset, rng
        self.t = preset.floor.wall_thickness / 2
        self.variants = 4  # models per class the asset library is asked for; indices wrap
        self.plates: dict[str, str] = {}  # room name -> its plate's label (identity.room_plates)

    def add(self, cls: str, kind: str, x: float, y: float, z: float, yaw: float, room: str, *,
            size: tuple[float, float, float] | None = None, blocks: bool = True, texture: int = -1,
            label: str | Callable[[float, float, float], str] = "", variant: int | None = None) -> None:
        """Append an object; a callable `label` is given the object's x, y and yaw (a cue showing where it hangs)."""
        if cls and cls not in self.scene.classes:
            cls = ""  # a class the site does not detect is still furniture
        if variant is None:
            variant = int(self.rng.integers(0, self.variants))
        x, y, yaw = float(x), float(y), float(math.atan2(math.sin(yaw), math.cos(yaw)))
        self.scene.objects.append(SceneObject(
            instance_id=len(self.scene.objects) + 1, cls=cls, kind=kind, x=x, y=y, z=float(z), yaw=yaw,
            size=size or _SIZES[kind], variant=variant, blocks_laser=blocks, room=room, texture=texture,
            label=label(x, y, yaw) if callable(label) else label,
        ))

    def on_wall(self, cls: str, kind: str, rect: Rect, side: str, along: float, z: float, room: str,
                blocks: bool = False, texture: int = -1, label: str | Callable[[float, float, float], str] = "",
                shifts: tuple[float, ...] = (0.0, 0.6, -0.6, 1.2, -1.2)) -> bool:
        """An object against the inside of `side` of `rect`, `along` metres from the side's start, slid by the
        first of `shifts` that keeps it off doors, windows and fixtures; whether it found a place."""
        w, d, _ = _SIZES[kind]
        inward = _NORMALS[_opposite(side)]
        off = self.t + d / 2 + 0.01
        for shift in shifts:
            a = along + shift
            if not w / 2 <= a <= _side_length(rect, side) - w / 2:
                continue
            if side in ("north", "south"):
                x, y = rect.x0 + a, (rect.y1 - off if side == "north" else rect.y0 + off)
            else:
                x, y = (rect.x1 - off if side == "east" else rect.x0 + off), rect.y0 + a
            if kind in _WALL_HUNG and self._covers_fixture(x, y, w):
                continue
            self.add(cls, kind, x, y, z, inward, room, blocks=blocks, texture=texture, label=label,
                     variant=0 if kind in identity.SIGNAGE_KINDS else None)
            return True
        return False

    def _covers_fixture(self, x: float, y: float, w: float, gap: float = 0.1) -> bool:
        return any(math.hypot(o.x - x, o.y - y) < (o.size[0] + w) / 2 + gap
                   for o in self.scene.objects if o.kind in _WALL_FIXTURES)


# Things hung on walls must not cover each other or a door or window (they would render on top).
_WALL_HUNG = {"poster", "fire_extinguisher", "exit_sign", *identity.SIGNAGE_KINDS}
_WALL_FIXTURES = {"door", "door_exterior", "window", "poster", "fire_extinguisher", "exit_sign",
                  *identity.SIGNAGE_KINDS}


def _opposite(side: str) -> str:
    return {"north": "south", "south": "north", "east": "west", "west": "east"}[side]


def _side_length(rect: Rect, side: str) -> float:
    return rect.w if side in ("north", "south") else rect.h


def furnish_scene(scene: Scene, preset: SitePreset, seed: int) -> Scene:
    """Place every object of the scene (in place) and return it."""
    rng = np.random.default_rng(seed + 7919)
    p = _Placer(scene, preset, rng)
    spec, cue_rng = preset.identity, identity.identity_rng(seed)
    if spec.wings > 1 or spec.wing_colours:
        identity.assign_wings(scene, spec.wings, spec.wing_floor_materials, cue_rng)
    if spec.room_types:
        identity.assign_room_types(scene, cue_rng)
    if spec.wing_colours:
        identity.paint_rooms(scene, spec.accent_wall_share, cue_rng)
    scene.outside_views = spec.outside_views
    scene.painted, scene.dado_height = spec.painted_walls, spec.dado_height if spec.painted_walls else 0.0
    p.plates = identity.room_plates(scene, spec.plate_names_share, cue_rng) if spec.room_plates else {}
    for wall in scene.walls:
        _wall_fixtures(p, wall)
    for room in scene.rooms:
        if room.kind == "corridor":
            _furnish_corridor(p, room, cue_rng)
        else:
            _furnish_room(p, room)
    if spec.desk_clutter:
        identity.desk_clutter(p, cue_rng)
    if spec.unique_pictures:
        identity.unique_pictures(scene)
    return scene


def _wall_fixtures(p: _Placer, wall) -> None:
    """Doors and windows sit in their wall openings; exterior doors get an exit sign above."""
    dx, dy = wall.direction
    normal = math.atan2(dx, -dy)  # left of the wall direction
    for o in wall.openings:
        cx, cy = wall.x0 + dx * (o.start + o.end) / 2, wall.y0 + dy * (o.start + o.end) / 2
        width = o.end - o.start
        room_name, _ = p.scene.room_at(cx + 0.3 * math.cos(normal), cy + 0.3 * math.sin(normal))
        inside = normal if room_name else normal + math.pi
        if o.kind == "window":
            p.add("window", "window", cx, cy, o.z0, inside, room_name, size=(width, wall.thickness + 0.04, o.z1 - o.z0),
                  blocks=False)
        elif o.kind == "door":
            kind = "door_exterior" if wall.exterior else "door"
            p.add("door", kind, cx, cy, 0.0, inside, room_name, size=(width, wall.thickness + 0.06, 2.05))
            if wall.exterior:
                p.add("exit_sign", "exit_sign", cx + 0.06 * math.cos(inside), cy + 0.06 * math.sin(inside), 2.25,
                      inside, room_name, blocks=False)
        elif o.kind == "doorway":
            # The open leaf swings into the room against the wall, hinge at the doorway's end.
            side = 1 if (p.rng.random() < 0.5) else -1
            room = p.scene.room_at(cx + 0.5 * math.cos(normal), cy + 0.5 * math.sin(normal))[0]
            into = normal if room and not room.startswith("corridor") else normal + math.pi
            hx, hy = cx + side * dx * width / 2, cy + side * dy * width / 2
            lx = hx + math.cos(into) * (width / 2 + 0.05)
            ly = hy + math.sin(into) * (width / 2 + 0.05)
            room_name = p.scene.room_at(lx, ly)[0]
            p.add("door", "door", lx, ly, 0.0, math.atan2(-side * dy, -side * dx), room_name,
                  size=(width, 0.05, 2.05))
            if room_name in p.plates:  # the room's number beside its door, on the corridor side
                identity.add_plate(p, p.plates[room_name], cx, cy, dx, dy, width, into + math.pi, room_name)


def _furnish_room(p: _Placer, room: Room) -> None:
    r, rng, f = room.rect, p.rng, p.preset.furnishing
    far = _opposite(room.door_side)
    sides = [s for s in ("north", "south", "east", "west") if s not in (room.door_side, far)]
    if room.kind in ("kitchen", "lounge", "storage"):
        _furnish_service_room(p, room, far, sides)
    elif room.kind == "meeting":
        _table_with_chairs(p, room, None)
        if p.preset.identity.room_boards:
            identity.room_board(p, room, [far, *sides[::-1]])
    else:
        length = _side_length(r, far)
        n_desks = max(1, int((length - 0.4) / 1.7))
        for k in range(n_desks):
            along = length * (k + 0.5) / n_desks
            if not p.on_wall("", "desk", r, far, along, 0.0, room.name, blocks=True):
                continue
            desk = p.scene.objects[-1]
            face = desk.yaw
            cx = desk.x + math.cos(face) * 0.7 + rng.normal(0, 0.08)
            cy = desk.y + math.sin(face) * 0.7 + rng.normal(0, 0.08)
            # chair front (-y of the model) points at the desk: its yaw is the desk's facing + pi/2 offset
            p.add("chair", "chair", cx, cy, 0.0, face + math.pi + rng.normal(0, 0.3), room.name)
        if p.preset.identity.room_boards:
            identity.room_board(p, room, [far, *sides[::-1]])
        if rng.random() < 0.6:
            p.on_wall("", "cabinet", r, sides[0], 0.6, 0.0, room.name, blocks=True)
        corner = rng.uniform(0.3, 0.6)
        p.on_wall("trash_bin", "trash_bin", r, far, corner, 0.0, room.name, blocks=True)
    lo, hi = f.plants_per_room
    for _ in range(int(rng.integers(lo, hi + 1))):
        side = sides[int(rng.integers(0, len(sides)))]
        p.on_wall("plant", "plant", r, side, _side_length(r, side) - 0.45, 0.0, room.name, blocks=True)
    lo, hi = f.posters_per_room
    for k in range(int(rng.integers(lo, hi + 1))):
        side = sides[k % len(sides)]
        along = _side_length(r, side) * rng.uniform(0.35, 0.65)
        p.on_wall("poster", "poster", r, side, along, 1.15, room.name, texture=int(rng.integers(0, f.poster_pictures)))
    if rng.random() < 0.25:
        p.on_wall("fire_extinguisher", "fire_extinguisher", r, room.door_side, 0.3, 0.0, room.name, blocks=True)


def _table_with_chairs(p: _Placer, room: Room, chairs: int | None) -> None:
    """A table in the middle, ringed by `chairs` chairs (None: 4 to 6)."""
    r, rng = room.rect, p.rng
    tw, td, _ = _SIZES["table"]
    yaw = 0.0 if r.w >= r.h else math.pi / 2
    p.add("", "table", r.cx, r.cy, 0.0, yaw, room.name)
    for k in range(int(rng.integers(4, 7)) if chairs is None else chairs):
        a = yaw + (k % 2) * math.pi
        along = (k // 2 - 1) * 0.6
        x = r.cx + math.cos(a) * (td / 2 + 0.35) - math.sin(a) * along
        y = r.cy + math.sin(a) * (td / 2 + 0.35) + math.cos(a) * along
        p.add("chair", "chair", x, y, 0.0, a + math.pi / 2 + rng.normal(0, 0.15), room.name)


def _furnish_service_room(p: _Placer, room: Room, far: str, sides: list[str]) -> None:
    """A kitchen (table, chairs, water cooler, cupboards), a lounge (sofas, a low table) or a storage room
    (cabinets along the walls): the room types that make one part of a floor unlike another."""
    r, rng = room.rect, p.rng
    if room.kind == "kitchen":
        _table_with_chairs(p, room, 4)
        p.on_wall("", "water_cooler", r, sides[0], 0.5, 0.0, room.name, blocks=True)
        for k in range(2):
            p.on_wall("", "cabinet", r, far, 0.5 + 0.85 * k, 0.0, room.name, blocks=True)
    elif room.kind == "lounge":
        p.on_wall("", "sofa", r, far, _side_length(r, far) / 2, 0.0, room.name, blocks=True)
        p.on_wall("", "sofa", r, sides[0], _side_length(r, sides[0]) / 2, 0.0, room.name, blocks=True)
        p.on_wall("", "whiteboard", r, sides[-1], _side_length(r, sides[-1]) / 2, 0.0, room.name, blocks=True)
    else:
        for side in (far, *sides):
            n = max(1, int((_side_length(r, side) - 0.6) / 0.9))
            for k in range(n):
                if rng.random() < 0.8:
                    p.on_wall("", "cabinet", r, side, 0.5 + 0.9 * k, 0.0, room.name, blocks=True, shifts=(0.0,))


def _furnish_corridor(p: _Placer, room: Room, cue_rng) -> None:
    """Identity cues near the junctions, then posters, extinguishers, exit signs, plants, bins (and notice
    boards when the preset has them) along both long walls, away from openings."""
    r, rng, f = room.rect, p.rng, p.preset.furnishing
    horizontal = r.w >= r.h
    long_sides = ("north", "south") if horizontal else ("east", "west")
    length = r.w if horizontal else r.h
    blocked = _blocked_spans(p.scene, r, horizontal)
    identity.corridor_cues(p, room, p.preset.identity, blocked, cue_rng)
    spec = p.preset.identity
    boards = (("notice_board", spec.notice_board_spacing, identity.HEIGHTS["notice_board"], False),) \
        if spec.notice_boards else ()
    for side in long_sides:
        for kind, spacing, z, blocks in (
            *boards,
            ("poster", f.corridor_poster_spacing, 1.15, False),
            ("fire_extinguisher", f.extinguisher_spacing, 0.0, True),
            ("exit_sign", f.exit_sign_spacing, 2.3, False),
            ("trash_bin", f.extinguisher_spacing * 1.3, 0.0, True),
            ("plant", f.extinguisher_spacing * 1.7, 0.0, True),
        ):
            along = rng.uniform(0.3, 1.0) * spacing
            while along < length - 0.5:
                pos = (r.x0 if horizontal else r.y0) + along
                width = _SIZES[kind][0]
                if not any(a - 0.2 < pos + width / 2 and pos - width / 2 < b + 0.2 for a, b in blocked):
                    tex = int(rng.integers(0, f.poster_pictures)) if kind == "poster" else -1
                    cls = "" if kind in identity.SIGNAGE_KINDS else kind
                    label = partial(identity.cue_label, p.scene, kind, k=0) if not cls else ""
                    p.on_wall(cls, kind, r, side, along, z, room.name, blocks=blocks, texture=tex, label=label)
                    blocked.append((pos - width / 2, pos + width / 2))
                along += spacing * rng.uniform(0.7, 1.3)


def _blocked_spans(scene: Scene, r: Rect, horizontal: bool) -> list[tuple[float, float]]:
    """Spans along a corridor where nothing may be hung: openings in its walls and crossing corridors."""
    spans = []
    for w in scene.walls:
        dx, dy = w.direction
        on_edge = (abs(dy) < 1e-9 and w.y0 in (r.y0, r.y1)) if horizontal else (abs(dx) < 1e-9 and w.x0 in (r.x0, r.x1))
        if not on_edge:
            continue
        for o in w.openings:
            a = (w.x0 if horizontal else w.y0) + o.start
            spans.append((a, a + (o.end - o.start)))
    for other in scene.rooms:
        if other.kind == "corridor" and other.name != "" and other.rect != r:
            o = other.rect
            if horizontal and o.y0 <= r.y1 and o.y1 >= r.y0:
                spans.append((o.x0, o.x1))
            if not horizontal and o.x0 <= r.x1 and o.x1 >= r.x0:
                spans.append((o.y0, o.y1))
    return spans
