"""Floor-plan generator: corridors with loops, rows of similar rooms, walls with doors and windows.

Corridor strips run wall to wall in both directions (so every pair of corridor lines closes a loop and
every corridor ends at an exterior door under an exit sign). The blocks between strips are filled with
rows of rooms that face the nearest corridor; whatever is too deep for rooms becomes a closed service
core (unknown in the map). Room widths come from a few standard sizes and doors sit at mirrored
positions, so many places look alike: the quasi-symmetry that makes indoor localization hard.
Objects are placed by `furnish.furnish_scene`.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from pipeline.sitegen.presets import SitePreset
from pipeline.sitegen.scene import Light, Opening, Rect, Room, Scene, Wall

DOOR_HEIGHT = 2.1
WINDOW_Z = (0.9, 2.1)


def corridor_lines(extent: float, n: int, band: float, width: float, jitter: float, rng) -> list[float]:
    """Lower edges of `n` corridor strips, the outer ones a band away from the walls."""
    edges = np.linspace(band, extent - band - width, n)
    edges[1:-1] += rng.uniform(-jitter, jitter, size=n - 2)
    edges[[0, -1]] += rng.uniform(-jitter, jitter, size=2) * 0.5
    return [float(round(e, 3)) for e in edges]


def _spans(extent: float, lines: list[float], width: float) -> list[tuple[float, float]]:
    """The intervals between corridor strips (blocks), from wall to wall."""
    bounds = [0.0] + [v for e in lines for v in (e, e + width)] + [extent]
    return [(bounds[i], bounds[i + 1]) for i in range(0, len(bounds), 2)]


def _split_row(length: float, widths: tuple[float, ...], rng) -> list[float]:
    """Room widths filling a row: standard widths, the remainder merged into the last room."""
    out: list[float] = []
    left = length
    while left >= min(widths) * 1.5 or not out:
        w = float(rng.choice(widths))
        if w > left:
            w = left
        out.append(w)
        left -= w
        if left < 1e-6:
            break
    if left > 1e-6:
        out[-1] += left
    return out


class _PlanBuilder:
    def __init__(self, preset: SitePreset, rng):
        self.p = preset
        self.rng = rng
        self.rooms: list[Room] = []
        self.closed: list[Rect] = []
        self.sides: list[tuple[str, float, float, float]] = []  # (orientation, coordinate, a0, a1)
        self.openings: list[tuple[str, float, Opening]] = []  # (orientation, coordinate, opening in map coords)
        self.doors: list[tuple[Room, float, float]] = []  # (room, door centre x, y) of each doorway

    def add_rect_sides(self, r: Rect) -> None:
        self.sides += [("h", r.y0, r.x0, r.x1), ("h", r.y1, r.x0, r.x1),
                       ("v", r.x0, r.y0, r.y1), ("v", r.x1, r.y0, r.y1)]

    def add_room(self, rect: Rect, facing: str, index_in_row: int, row_len: int, kind: str) -> None:
        fp = self.p.floor
        name = f"R{len([r for r in self.rooms if r.kind != 'corridor']):02d}"
        along_x = facing in ("north", "south")
        lo, hi = (rect.x0, rect.x1) if along_x else (rect.y0, rect.y1)
        half = fp.door_width / 2
        # Doors mirrored about the row's middle: rooms in the first half open near their far end.
        near_end = index_in_row < row_len / 2
        centre = (hi - 0.35 - half) if near_end else (lo + 0.35 + half)
        centre = float(np.clip(centre, lo + half + 0.1, hi - half - 0.1))
        coord = {"north": rect.y1, "south": rect.y0, "east": rect.x1, "west": rect.x0}[facing]
        orient = "h" if along_x else "v"
        self.openings.append((orient, coord, Opening(centre - half, centre + half, 0.0, DOOR_HEIGHT, "doorway")))
        if along_x:
            a, b = Rect(rect.x0, rect.y0, rect.x1, rect.cy), Rect(rect.x0, rect.cy, rect.x1, rect.y1)
            near, far = (b, a) if facing == "north" else (a, b)
        else:
            a, b = Rect(rect.x0, rect.y0, rect.cx, rect.y1), Rect(rect.cx, rect.y0, rect.x1, rect.y1)
            near, far = (b, a) if facing == "east" else (a, b)
        room = Room(name, kind, rect, (("door", near), ("window", far)), int(self.rng.integers(0, 2)), facing)
        self.rooms.append(room)
        door_xy = (centre, coord) if along_x else (coord, centre)
        self.doors.append((room, *door_xy))
        self.add_rect_sides(rect)

    def fill_block(self, bx: tuple[float, float], by: tuple[float, float], W: float, H: float) -> None:
        fp = self.p.floor
        corridor = {"west": bx[0] > 0, "east": bx[1] < W, "south": by[0] > 0, "north": by[1] < H}
        w, h = bx[1] - bx[0], by[1] - by[0]
        along_x = w >= h
        if along_x and not (corridor["north"] or corridor["south"]):
            along_x = False
        if not along_x and not (corridor["east"] or corridor["west"]):
            along_x = True
        if along_x:
            lo_side, hi_side, depth_total, (a0, a1), (d0, d1) = "south", "north", h, bx, by
        else:
            lo_side, hi_side, depth_total, (a0, a1), (d0, d1) = "west", "east", w, by, bx
        facing = [s for s in (lo_side, hi_side) if corridor[s]]
        if len(facing) == 2 and depth_total < 2 * fp.min_room_depth:
            facing = [lo_side]
        depth = min(fp.max_room_depth, depth_total / len(facing))
        rows = []
        for side in facing:
            rows.append((side, (d0, d0 + depth) if side == lo_side else (d1 - depth, d1)))
        widths = _split_row(a1 - a0, fp.room_widths, self.rng)
        used: list[tuple[float, float]] = []
        for side, (r0, r1) in rows:
            pos = a0
            for i, width in enumerate(widths if side == facing[0] else widths[::-1]):
                kind = "meeting" if self.rng.random() < self.p.furnishing.meeting_room_share else "office"
                rect = Rect(pos, r0, pos + width, r1) if along_x else Rect(r0, pos, r1, pos + width)
                self.add_room(rect, side, i, len(widths), kind)  # a row on the south side faces south
                pos += width
            used.append((r0, r1))
        # What rooms do not fill becomes a closed core.
        used.sort()
        gaps, cursor = [], d0
        for r0, r1 in used:
            if r0 - cursor > 0.05:
                gaps.append((cursor, r0))
            cursor = max(cursor, r1)
        if d1 - cursor > 0.05:
            gaps.append((cursor, d1))
        for g0, g1 in gaps:
            core = Rect(a0, g0, a1, g1) if along_x else Rect(g0, a0, g1, a1)
            self.closed.append(core)
            self.add_rect_sides(core)


def _merge_walls(builder: _PlanBuilder, preset: SitePreset, W: float, H: float, rng) -> list[Wall]:
    fp = preset.floor
    groups: dict[tuple[str, float], list[tuple[float, float]]] = defaultdict(list)
    for orient, coord, a0, a1 in builder.sides:
        groups[(orient, round(coord, 6))].append((a0, a1))
    # The building outline closes the corridor ends.
    for orient, coord, extent in (("h", 0.0, W), ("h", H, W), ("v", 0.0, H), ("v", W, H)):
        groups[(orient, coord)].append((0.0, extent))
    walls = []
    n_materials = 3
    for (orient, coord), intervals in sorted(groups.items()):
        intervals.sort()
        merged = [list(intervals[0])]
        for a0, a1 in intervals[1:]:
            if a0 <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], a1)
            else:
                merged.append([a0, a1])
        exterior = coord in (0.0, W if orient == "v" else H)
        for a0, a1 in merged:
            ops = sorted(
                (Opening(o.start - a0, o.end - a0, o.z0, o.z1, o.kind) for ori, c, o in builder.openings
                 if ori == orient and abs(c - coord) < 1e-6 and o.start >= a0 - 1e-6 and o.end <= a1 + 1e-6),
                key=lambda o: o.start,
            )
            x0, y0, x1, y1 = (a0, coord, a1, coord) if orient == "h" else (coord, a0, coord, a1)
            material = 0 if exterior else int(rng.integers(1, n_materials))
            walls.append(Wall(x0, y0, x1, y1, fp.wall_thickness, fp.wall_height, material, exterior, tuple(ops)))
    return walls


def generate_plan(preset: SitePreset, seed: int) -> Scene:
    """The floor plan of a preset: rooms, corridors, closed cores, walls with openings, ceiling lights.

    Objects are added by `pipeline.sitegen.furnish.furnish_scene`; this returns a scene without them.
    """
    rng = np.random.default_rng(seed)
    fp = preset.floor
    W, H = fp.size
    c = fp.corridor_width
    xs = corridor_lines(W, fp.corridors_x, fp.band_depth, c, fp.jitter, rng)
    ys = corridor_lines(H, fp.corridors_y, fp.band_depth, c, fp.jitter, rng)
    b = _PlanBuilder(preset, rng)
    for bx in _spans(W, xs, c):
        for by in _spans(H, ys, c):
            b.fill_block(bx, by, W, H)

    corridor_rooms = []
    for j, y in enumerate(ys):
        strip = Rect(0.0, y, W, y + c)
        cuts = [0.0] + [x + c / 2 for x in xs] + [W]
        areas = tuple((f"s{k}", Rect(cuts[k], y, cuts[k + 1], y + c)) for k in range(len(cuts) - 1))
        corridor_rooms.append(Room(f"corridor_h{j}", "corridor", strip, areas, 2))
    for i, x in enumerate(xs):
        cuts = [0.0] + [v for y in ys for v in (y, y + c)] + [H]
        for k in range(0, len(cuts), 2):
            piece = Rect(x, cuts[k], x + c, cuts[k + 1])
            corridor_rooms.append(Room(f"corridor_v{i}_{k // 2}", "corridor", piece, (("s0", piece),), 2))
    # Exterior doors at both ends of every corridor, with the wall's outline coordinates.
    for y in ys:
        for xw in (0.0, W):
            b.openings.append(("v", xw, Opening(y + c / 2 - 0.8, y + c / 2 + 0.8, 0.0, DOOR_HEIGHT, "door")))
    for x in xs:
        for yw in (0.0, H):
            b.openings.append(("h", yw, Opening(x + c / 2 - 0.8, x + c / 2 + 0.8, 0.0, DOOR_HEIGHT, "door")))
    _add_windows(b, preset, W, H)

    walls = _merge_walls(b, preset, W, H, rng)
    lights = [Light(x, y, fp.wall_height - 0.05, 1.0) for room in corridor_rooms + b.rooms
              for x, y in _light_grid(room.rect, preset.render.light_spacing)]
    return Scene(
        name=preset.name, seed=seed, bounds=Rect(0.0, 0.0, W, H), walls=walls,
        rooms=corridor_rooms + b.rooms, objects=[], lights=lights, wall_height=fp.wall_height,
        classes=tuple(preset.furnishing.classes), closed=b.closed,
    )


def _add_windows(b: _PlanBuilder, preset: SitePreset, W: float, H: float) -> None:
    spacing, width = preset.furnishing.window_spacing, 1.2
    for room in b.rooms:
        r = room.rect
        for orient, coord, lo, hi, on_outline in (
            ("h", r.y0, r.x0, r.x1, r.y0 == 0.0), ("h", r.y1, r.x0, r.x1, r.y1 == H),
            ("v", r.x0, r.y0, r.y1, r.x0 == 0.0), ("v", r.x1, r.y0, r.y1, r.x1 == W),
        ):
            if not on_outline:
                continue
            n = max(1, int((hi - lo - 0.8) // spacing))
            centres = lo + (hi - lo) * (np.arange(n) + 0.5) / n
            for cen in centres:
                b.openings.append((orient, coord, Opening(cen - width / 2, cen + width / 2, *WINDOW_Z, "window")))


def _light_grid(rect: Rect, spacing: float) -> list[tuple[float, float]]:
    nx, ny = max(1, math.floor(rect.w / spacing)), max(1, math.floor(rect.h / spacing))
    return [(rect.x0 + rect.w * (i + 0.5) / nx, rect.y0 + rect.h * (j + 0.5) / ny)
            for i in range(nx) for j in range(ny)]
