"""Identity cues of a reference site: wings, room numbers and plates, signage, room types, desk clutter.

Real buildings are repetitive but carry identity by law and habit: a number plate by every office door,
escape plans and directory signs at junctions, notice boards, wings painted in their own colour, a
kitchen here and a lounge there. Each cue is a switch of the preset's `identity` section; with all off
the floor is the plain repetitive one (the `twins` preset). Cues draw from their own random stream
(seed + IDENTITY_SALT), and the wall-hung ones are thin and above the laser's plane: they do not block
it, so the occupancy map is that of the same floor without them.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import partial

import numpy as np

from pipeline.sitegen.scene import Rect, Room, Scene, Wing

IDENTITY_SALT = 5557
WING_COLOURS = ((0.25, 0.45, 0.80), (0.90, 0.50, 0.15), (0.30, 0.65, 0.35), (0.80, 0.25, 0.35),
                (0.85, 0.75, 0.20), (0.20, 0.65, 0.70), (0.55, 0.35, 0.70), (0.55, 0.40, 0.25))
SURNAMES = ("Weber", "Chen", "Okafor", "Silva", "Nakamura", "Novak", "Dubois", "Rossi", "Kowalski", "Haddad",
            "Johansson", "Patel", "Garcia", "Müller", "Ivanova", "O'Brien", "Kim", "Yilmaz", "Schmidt", "Costa",
            "Lindqvist", "Moreau", "Tanaka", "Nguyen", "Fischer", "Jensen", "Ali", "Popescu", "Brown", "Santos")
MEETING_NAMES = ("Turing", "Curie", "Lovelace", "Noether", "Gauss", "Hopper", "Shannon", "Euler", "Kepler",
                 "Meitner", "Fourier", "Bayes", "Hypatia", "Tesla", "Darwin", "Franklin")
SIGNAGE_KINDS = ("plate", "notice_board", "escape_plan", "sign")
SIZES = {"plate": (0.2, 0.015, 0.125), "notice_board": (1.0, 0.03, 0.75), "escape_plan": (0.42, 0.012, 0.315),
         "sign": (0.8, 0.025, 0.2), "clutter": (0.9, 0.4, 0.45), "sofa": (1.8, 0.85, 0.85),
         "water_cooler": (0.35, 0.35, 1.1), "whiteboard": (1.5, 0.55, 1.8)}
ROOM_BOARD_Z = 1.25  # bottom edge of a room's pinboard, above desks (0.75 m) and their monitors
HEIGHTS = {"plate": 1.45, "notice_board": 1.0, "escape_plan": 1.35, "sign": 1.9}  # of the bottom edge, m


def identity_rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed + IDENTITY_SALT)


def _grid(n: int, aspect: float) -> tuple[int, int]:
    """(columns, rows) with columns * rows == n whose cells are closest to square on a floor of `aspect`."""
    pairs = [(c, n // c) for c in range(1, n + 1) if n % c == 0]
    return min(pairs, key=lambda cr: abs(math.log(aspect * cr[1] / cr[0])))


def assign_wings(scene: Scene, n: int, n_floor_materials: int, rng: np.random.Generator) -> None:
    """`n` wings A, B, ... on a grid over the floor, each with a colour and a floor material."""
    b = scene.bounds
    cols, rows = _grid(n, b.w / b.h)
    colours = [WING_COLOURS[i] for i in rng.permutation(len(WING_COLOURS))]
    wings = []
    for k in range(n):
        c, r = k % cols, k // cols
        rect = Rect(b.x0 + b.w * c / cols, b.y0 + b.h * r / rows, b.x0 + b.w * (c + 1) / cols,
                    b.y0 + b.h * (r + 1) / rows)
        wings.append(Wing(chr(ord("A") + k), rect, colours[k % len(colours)], k % max(1, n_floor_materials)))
    scene.wings = wings


def assign_room_types(scene: Scene, rng: np.random.Generator) -> None:
    """Per wing, one office becomes a kitchen, a second a lounge and a third a storage room where the wing
    has enough offices; furnishing then differs by type."""
    rooms = list(scene.rooms)
    for wing in scene.wings or [None]:
        offices = [i for i, r in enumerate(rooms) if r.kind == "office"
                   and (wing is None or scene.wing_at(r.rect.cx, r.rect.cy) is wing)]
        chosen = rng.permutation(offices)
        for kind, need in (("kitchen", 3), ("lounge", 7), ("storage", 10)):
            if len(offices) >= need and len(chosen):
                i, chosen = int(chosen[0]), chosen[1:]
                rooms[i] = replace(rooms[i], kind=kind)
    scene.rooms = rooms


def room_plates(scene: Scene, names_share: float, rng: np.random.Generator) -> dict[str, str]:
    """Room name -> plate label "NUMBER|NAME": wing letter + 1 + a two-digit index, numbered along the
    floor (by row, then x), so every number on a floor is distinct; names by room type."""
    labels: dict[str, str] = {}
    surnames = list(rng.permutation(SURNAMES))
    meetings = list(rng.permutation(MEETING_NAMES))
    rooms = [r for r in scene.rooms if r.kind != "corridor"]
    for wing in scene.wings or [Wing("", scene.bounds, (0.5, 0.5, 0.5), 0)]:
        mine = [r for r in rooms if not scene.wings or scene.wing_at(r.rect.cx, r.rect.cy) is wing]
        mine.sort(key=lambda r: (round(r.rect.cy / 3.0), r.rect.cx))
        for k, room in enumerate(mine):
            number = f"{wing.letter}{101 + k}"
            if room.kind == "meeting":
                name = f"{meetings.pop() if meetings else 'Meeting'} room"
            elif room.kind in ("kitchen", "lounge", "storage"):
                name = room.kind.capitalize()
            elif rng.random() < names_share:
                name = f"{chr(ord('A') + int(rng.integers(0, 26)))}. {surnames[k % len(surnames)]}"
            else:
                name = ""
            labels[room.name] = f"{number}|{name}"
    return labels


def paint_rooms(scene: Scene, accent_share: float, rng: np.random.Generator) -> None:
    """Room walls: a light tint of the wing's colour, and for `accent_share` of the rooms a colour of their own."""
    for room in scene.rooms:
        if room.kind == "corridor":
            continue
        wing = scene.wing_at(room.rect.cx, room.rect.cy)
        base = np.asarray(wing.colour if wing else (1.0, 1.0, 1.0))
        if rng.random() < accent_share:
            colour = 0.55 + 0.45 * rng.uniform(0.2, 1.0, 3)
        else:
            colour = 0.88 + 0.12 * base
        scene.paint[room.name] = tuple(float(v) for v in colour)


def surface_at(scene: Scene, x: float, y: float, n_materials: int) -> tuple[int, tuple[float, float, float]]:
    """(wall material, tint) of the wall surface facing the point (x, y): rooms wear the first material in
    their paint, corridors their wing's material and a strong tint of its colour."""
    name, _ = scene.room_at(x, y)
    if name in scene.paint:
        return 0, scene.paint[name]
    wing = scene.wing_at(x, y)
    if wing is None:
        return 0, (1.0, 1.0, 1.0)
    material = (ord(wing.letter) - ord("A")) % max(1, n_materials)
    return material, tuple(float(0.3 + 0.7 * c) for c in wing.colour)  # type: ignore[return-value]


PAINT = -1  # the material index of smooth paint (`paint_texture`), beside the library's wall textures
DADO_RAIL_M = 0.04  # a darker rail on top of a corridor's dado


def surface_bands(scene: Scene, x: float, y: float, n_materials: int) -> list[tuple[float, int, tuple]]:
    """The wall surface facing the point (x, y) as bands from the floor up: (top of the band in metres, material,
    tint), the last band reaching the ceiling. Unpainted: one band, `surface_at`'s. Painted (`scene.painted`):
    rooms in their paint (white without one); corridors light above a dado in their wing's full colour (a real
    building's colour scheme: the colour reads as colour on smooth paint, where a tinted roughcast reads as
    texture), white without wings."""
    if not scene.painted:
        return [(math.inf, *surface_at(scene, x, y, n_materials))]
    name, _ = scene.room_at(x, y)
    if name in scene.paint:
        return [(math.inf, PAINT, scene.paint[name])]
    wing = scene.wing_at(x, y)
    if wing is None or (name and not name.startswith("corridor")):  # no wings, or a room without a colour: white
        return [(math.inf, PAINT, (1.0, 1.0, 1.0))]
    colour = np.asarray(wing.colour)
    light = tuple(float(v) for v in 0.82 + 0.18 * colour)
    if scene.dado_height <= 0:
        return [(math.inf, PAINT, light)]
    dado = tuple(float(v) for v in 0.15 + 0.8 * colour)
    rail = tuple(float(v) for v in 0.6 * colour)
    return [(scene.dado_height, PAINT, dado), (scene.dado_height + DADO_RAIL_M, PAINT, rail), (math.inf, PAINT, light)]


def paint_texture(size: int = 128) -> np.ndarray:
    """Smooth matt paint: near-white with a faint roller mottle, (size, size, 3) uint8, tinted by the mesh colour."""
    rng = np.random.default_rng(IDENTITY_SALT)
    coarse = rng.random((size // 16, size // 16))
    mottle = np.kron(coarse, np.ones((16, 16)))
    fine = rng.random((size, size))
    value = 0.93 + 0.025 * (mottle - 0.5) + 0.015 * (fine - 0.5)
    return (np.clip(value, 0, 1)[..., None] * np.ones(3) * 255).astype(np.uint8)


def floor_tint(scene: Scene, x: float, y: float) -> tuple[float, float, float]:
    wing = scene.wing_at(x, y)
    return tuple(float(0.75 + 0.25 * c) for c in wing.colour) if wing else (1.0, 1.0, 1.0)  # type: ignore[return-value]


def add_plate(p, label: str, cx: float, cy: float, dx: float, dy: float, width: float, corridor_yaw: float,
              room: str) -> None:
    """A plate on the corridor face of the wall, beside the doorway centred at (cx, cy) along (dx, dy)."""
    w, d, h = SIZES["plate"]
    off = p.t + d / 2 + 0.005
    nx, ny = math.cos(corridor_yaw), math.sin(corridor_yaw)
    for side in (1.0, -1.0):
        a = side * (width / 2 + 0.12 + w / 2)
        x, y = cx + dx * a + nx * off, cy + dy * a + ny * off
        if not p._covers_fixture(x, y, w, gap=0.05):
            p.add("", "plate", x, y, HEIGHTS["plate"], corridor_yaw, room, size=SIZES["plate"], blocks=False,
                  label=label)
            return


def corridor_cues(p, room: Room, spec, blocked: list[tuple[float, float]], rng: np.random.Generator) -> None:
    """Escape plans, signs and notice boards on the corridor's long walls near each junction it meets."""
    r = room.rect
    horizontal = r.w >= r.h
    length = r.w if horizontal else r.h
    start = r.x0 if horizontal else r.y0
    ends = _junctions(p.scene, r) or [start + length / 2]
    kinds = [k for k, on in (("escape_plan", spec.escape_plans), ("sign", spec.signs),
                             ("notice_board", spec.notice_boards)) if on]
    if not kinds:
        return
    sides = ("north", "south") if horizontal else ("east", "west")
    for j, c in enumerate(ends):
        for s, side in enumerate(sides):
            kind = kinds[(j + s) % len(kinds)]
            w = SIZES[kind][0]
            for along in (c - start + 2.2 + w / 2, c - start - 2.2 - w / 2, c - start + 3.5, c - start - 3.5):
                pos = start + along
                if not (w / 2 < along < length - w / 2):
                    continue
                if any(a - 0.15 < pos + w / 2 and pos - w / 2 < b + 0.15 for a, b in blocked):
                    continue
                if p.on_wall("", kind, r, side, along, HEIGHTS[kind], room.name, blocks=False, shifts=(0.0,),
                             label=partial(cue_label, p.scene, kind, k=j * 2 + s)):
                    blocked.append((pos - w / 2, pos + w / 2))
                    break


def _junctions(scene: Scene, r: Rect) -> list[float]:
    """Where other corridors meet corridor `r`, as coordinates along its long axis: the centres of the
    corridors crossing a full-length strip, or the ends of a piece between two strips."""
    horizontal = r.w >= r.h
    out = []
    for o in scene.rooms:
        q = o.rect
        if o.kind != "corridor" or q == r:
            continue
        touches_y = abs(q.y0 - r.y1) < 1e-6 or abs(q.y1 - r.y0) < 1e-6
        if horizontal and q.h > q.w and q.x0 < r.x1 and q.x1 > r.x0 and touches_y:
            out.append((q.x0 + q.x1) / 2)
        if not horizontal and q.w >= q.h and q.x0 < r.x1 and q.x1 > r.x0 and touches_y:
            out.append(r.y0 if abs(q.y1 - r.y0) < 1e-6 else r.y1)
    return sorted(set(out))


def cue_label(scene: Scene, kind: str, x: float, y: float, yaw: float, k: int) -> str:
    """What a cue shows, as a key the texture is drawn from (`sitegen.textures`)."""
    if kind == "escape_plan":
        return f"plan:{x:.2f}:{y:.2f}:{yaw:.3f}"
    if kind == "notice_board":
        return f"board:{x:.2f}:{y:.2f}:v0"
    # A sign names the wings left and right of where it hangs, as seen facing it.
    lx, ly = -math.sin(yaw), math.cos(yaw)  # the viewer's left, facing the sign (the sign faces `yaw`)
    left = scene.wing_at(x - 6 * lx, y - 6 * ly)
    right = scene.wing_at(x + 6 * lx, y + 6 * ly)
    if left is None or right is None:
        return f"sign:Exit ^:Rooms {k + 1} <"
    if left is right:
        return f"sign:Wing {left.letter} ^:Exit >"
    return f"sign:Wing {left.letter} <:Wing {right.letter} >"


def room_board(p, room: Room, sides: list[str]) -> None:
    """A pinboard of the room's own, on the first of `sides` (the desks' wall first) where one fits clear of
    windows and fixtures near the wall's middle; its notes are keyed by where it hangs, so no two boards of a
    floor show the same."""
    for side in sides:
        length = room.rect.w if side in ("north", "south") else room.rect.h
        for shift in (0.0, 0.8, -0.8):
            if p.on_wall("", "notice_board", room.rect, side, length / 2 + shift, ROOM_BOARD_Z, room.name,
                         blocks=False, shifts=(0.0,), label=partial(cue_label, p.scene, "notice_board", k=0)):
                return


def desk_clutter(p, rng: np.random.Generator) -> None:
    """A monitor, books and papers on most desks, a different arrangement on each."""
    for desk in [o for o in p.scene.objects if o.kind == "desk"]:
        if rng.random() < 0.15:
            continue
        back = 0.12
        x = desk.x - math.cos(desk.yaw) * back
        y = desk.y - math.sin(desk.yaw) * back
        p.add("", "clutter", x, y, desk.size[2], desk.yaw, desk.room, size=SIZES["clutter"], blocks=False,
              variant=int(rng.integers(0, 1 << 16)))


def unique_pictures(scene: Scene) -> None:
    """Every poster of the floor gets its own picture of the site's pool (index = its order of placement)."""
    k = 0
    for i, o in enumerate(scene.objects):
        if o.cls == "poster":
            scene.objects[i] = replace(o, texture=k)
            k += 1
