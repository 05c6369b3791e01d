"""Moving an interior wall of a scene: the building refitted (`siteloc synth --move-wall`).

A partition between two rooms, or between a room and a corridor, moves across itself; its doors, what hangs on it,
the walls that end on it and the furniture in its way follow (the rules are below). `change_scene` calls
`move_wall` when `ChangeSpec.move_wall_m` is set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from pipeline.sitegen.identity import SIGNAGE_KINDS
from pipeline.sitegen.scene import Light, Opening, Rect, Room, Scene, SceneObject, Wall

# --- Moving an interior wall ---------------------------------------------------------------------------------------
#
# A partition between two rooms, or between a room and a corridor, moves across itself (a refit: one room grows, its
# neighbour shrinks). Only a wall whose rooms stay rectangles may move: rooms lie along it from end to end on both
# sides (so an outer wall, a wall of a closed core or the side of a long corridor never moves), and the rooms it moves
# into keep `MIN_ROOM_M`. Its doors and whatever hangs on it or swings from its doorways move with it; walls that end
# on it follow it (shortened or lengthened, their openings kept in place), and walls it ends on must have no door or
# window where its end comes to rest. Furniture in its way is pushed ahead of it (and what that pushes, and what
# stands on a pushed desk), or taken out where it would leave its room, stand in a doorway or in other furniture; a
# door or window in the way rules the move out. Map, laser world and meshes all come from the scene's walls and
# objects, so they all show the moved wall.

WALL_SALT = 15485863  # the wall move's own random stream
MIN_ROOM_M = 1.5  # a room or corridor the wall moves into keeps at least this depth
WALL_GAP_M = 0.05  # furniture pushed by the wall stops this far from its face
OPENING_CLEAR_M = 0.15  # a moved wall's end stays this far (past its half thickness) from a door or window
DOORWAY_CLEAR_M = 0.8  # pushed furniture keeps out of this depth in front of and behind every doorway
PASSAGE_M = 0.5  # furniture that the moved wall's doorways come to within this depth of moves out of their way
_EPS = 1e-6
_HUNG = {"poster", "fire_extinguisher", "exit_sign", "window", "door", "door_exterior", *SIGNAGE_KINDS}
_NEVER_PUSHED = {"door", "door_exterior", "window"}  # in the wall's way: that wall does not move

RectPose = tuple[float, float, float, float, float]  # (cx, cy, yaw, width along local x, depth along local y)


@dataclass(frozen=True)
class WallMove:
    """`scene.walls[wall]` moved from `before` to `after` ((x0, y0, x1, y1)) by `distance` metres into the rooms
    `into` (they shrink); the rooms `grows` on its other side grow."""

    wall: int
    before: tuple[float, float, float, float]
    after: tuple[float, float, float, float]
    distance: float
    into: tuple[str, ...]
    grows: tuple[str, ...]

    @property
    def rooms(self) -> tuple[str, ...]:
        return tuple(sorted(self.into + self.grows))

    def record(self) -> dict:
        """For a report: the rooms beside the wall, its end points before and after, the distance."""
        def ends(s):
            return [[round(float(s[0]), 4), round(float(s[1]), 4)], [round(float(s[2]), 4), round(float(s[3]), 4)]]

        return {"rooms": list(self.rooms), "into": list(self.into), "grows": list(self.grows),
                "from": ends(self.before), "to": ends(self.after), "distance_m": round(self.distance, 4)}


@dataclass(frozen=True)
class _Plan:
    move: WallMove
    walls: list[Wall]  # the scene's walls after the move
    rooms: list[Room]  # the scene's rooms after the move (the rooms beside the wall resized, areas too)
    orient: str  # "h": the wall runs along x (y = line); "v": along y
    line: float  # its old line
    span: tuple[float, float]  # its extent along itself
    step: tuple[float, float]  # the unit direction it moves in
    band: tuple[float, float]  # (from, to) metres along `step` from the old line: its way, where nothing may stay

    def band_rect(self) -> RectPose:
        return self.strip(*self.span, *self.band)

    def strip(self, a0: float, a1: float, b0: float, b1: float) -> RectPose:
        """The rectangle from a0 to a1 along the wall and from b0 to b1 metres along `step` from its old line."""
        mid_a, mid_u = (a0 + a1) / 2, self.line + (self.step[0] + self.step[1]) * (b0 + b1) / 2
        if self.orient == "h":
            return mid_a, mid_u, 0.0, a1 - a0, b1 - b0
        return mid_u, mid_a, math.pi / 2, a1 - a0, b1 - b0

    def across(self, pts: np.ndarray) -> np.ndarray:
        """Metres along the move's direction from the old line, of points (N, 2)."""
        origin = np.array([self.line, 0.0] if self.orient == "v" else [0.0, self.line])
        return (pts - origin) @ np.asarray(self.step)


def choose_wall_move(scene: Scene, seed: int, distance: float, areas: tuple[str, ...] = ()) -> WallMove | None:
    """The interior wall that `change_scene` moves by `distance` metres (seeded, among every wall that may; with
    `areas`, one beside one of their rooms), or None when none may."""
    plan = _choose(scene, seed, distance, areas)
    return plan.move if plan is not None else None


def _choose(scene: Scene, seed: int, distance: float, areas: tuple[str, ...]) -> _Plan | None:
    if not distance > 0:
        raise ValueError(f"a wall moves by a positive distance, not {distance}")
    rooms = {a.split("/", 1)[0] for a in areas}
    plans = [p for i in range(len(scene.walls)) for sign in (1, -1)
             if (p := _plan(scene, i, sign, float(distance))) is not None
             and (not rooms or set(p.move.rooms) & rooms)]
    if not plans:
        return None
    return plans[int(np.random.default_rng(seed + WALL_SALT).integers(len(plans)))]


def _frame(wall: Wall) -> tuple[str, float, float, float] | None:
    """("h", y, x from, x to) of a horizontal wall, ("v", x, y from, y to) of a vertical one; None if slanted."""
    if abs(wall.y1 - wall.y0) < _EPS:
        return "h", wall.y0, min(wall.x0, wall.x1), max(wall.x0, wall.x1)
    if abs(wall.x1 - wall.x0) < _EPS:
        return "v", wall.x0, min(wall.y0, wall.y1), max(wall.y0, wall.y1)
    return None


def _across(r: Rect, orient: str) -> tuple[float, float]:
    return (r.y0, r.y1) if orient == "h" else (r.x0, r.x1)


def _along(r: Rect, orient: str) -> tuple[float, float]:
    return (r.x0, r.x1) if orient == "h" else (r.y0, r.y1)


def _moved_edge(r: Rect, orient: str, old: float, new: float) -> Rect:
    """`r` with whichever of its edges lies on the line `old` (across `orient`) put on `new`."""
    if orient == "h":
        return replace(r, y0=new if abs(r.y0 - old) < _EPS else r.y0, y1=new if abs(r.y1 - old) < _EPS else r.y1)
    return replace(r, x0=new if abs(r.x0 - old) < _EPS else r.x0, x1=new if abs(r.x1 - old) < _EPS else r.x1)


def _plan(scene: Scene, i: int, sign: int, d: float) -> _Plan | None:
    """Wall `i` moved by `d` metres towards growing (`sign` 1) or shrinking (-1) y or x, or None if it may not."""
    wall = scene.walls[i]
    frame = _frame(wall)
    if wall.exterior or frame is None:
        return None
    orient, c, a0, a1 = frame
    c2, t = c + sign * d, wall.thickness
    lo, hi = min(c, c2) - t / 2, max(c, c2) + t / 2  # what the wall sweeps
    rooms, into, grows, cover = list(scene.rooms), [], [], {1: 0.0, -1: 0.0}
    for k, room in enumerate(scene.rooms):
        (u0, u1), (v0, v1) = _across(room.rect, orient), _along(room.rect, orient)
        if min(v1, a1) - max(v0, a0) <= _EPS:
            continue
        side = 1 if abs(u0 - c) < _EPS else -1 if abs(u1 - c) < _EPS else 0
        if side == 0:
            if u1 > lo and u0 < hi:
                return None  # the wall runs through a room, or a room lies in its way
            continue
        if v0 < a0 - _EPS or v1 > a1 + _EPS:
            return None  # the room goes on past the wall's end: it would not stay a rectangle
        if side == sign and (u1 - u0) - d < MIN_ROOM_M:
            return None
        areas = tuple((name, _moved_edge(r, orient, c, c2)) for name, r in room.areas)
        if any(min(r.w, r.h) < 0.3 for _, r in areas):
            return None
        rooms[k] = replace(room, rect=_moved_edge(room.rect, orient, c, c2), areas=areas)
        cover[side] += v1 - v0
        (into if side == sign else grows).append(room.name)
    if any(abs(v - (a1 - a0)) > 1e-3 for v in cover.values()):
        return None  # not rooms (or corridors) from end to end on both sides: an outer wall, a core's
    for r in scene.closed:
        (u0, u1), (v0, v1) = _across(r, orient), _along(r, orient)
        if min(v1, a1) - max(v0, a0) > -_EPS and u1 > lo - _EPS and u0 < hi + _EPS:
            return None
    walls = list(scene.walls)
    walls[i] = replace(wall, y0=c2, y1=c2) if orient == "h" else replace(wall, x0=c2, x1=c2)
    for j, other in enumerate(scene.walls):
        if j == i:
            continue
        f = _frame(other)
        if f is None:
            return None
        o_orient, oc, o0, o1 = f
        if o_orient == orient:
            if min(o1, a1) - max(o0, a0) > -_EPS and lo - t <= oc <= hi + t:
                return None  # a parallel wall in the way, or continuing this one
            continue
        if not a0 - _EPS <= oc <= a1 + _EPS or o1 < lo - _EPS or o0 > hi + _EPS:
            continue  # beside the wall's span, or clear of its way
        if abs(o0 - c) < _EPS or abs(o1 - c) < _EPS:  # it ends on the wall: its end follows
            moved = _end_moved(other, orient, c, c2, t)
            if moved is None:
                return None
            walls[j] = moved
        elif o0 < c - _EPS and o1 > c + _EPS:  # the wall ends on it (or crosses it): the new junction must be clear
            if not o0 + t / 2 <= c2 <= o1 - t / 2 or not _clear_of_openings(other, orient, c2, t):
                return None
        else:
            return None  # a wall ending in its way
    new = walls[i]
    move = WallMove(i, (wall.x0, wall.y0, wall.x1, wall.y1), (new.x0, new.y0, new.x1, new.y1), d,
                    tuple(into), tuple(grows))
    step = (0.0, float(sign)) if orient == "h" else (float(sign), 0.0)
    plan = _Plan(move, walls, rooms, orient, c, (a0, a1), step, (t / 2 - 0.02, d + t / 2 + WALL_GAP_M))
    return plan if _apply_objects(plan, scene, scene.objects) is not None else None  # None: a door in the way


def _end_moved(wall: Wall, orient: str, c: float, c2: float, t: float) -> Wall | None:
    """A wall across the moved one, its end on the line `c` put on `c2` and its openings kept where they are;
    None when it would get too short or a door or window would come near the new junction."""
    k0, k1 = ("y0", "y1") if orient == "h" else ("x0", "x1")  # the moved wall's across axis is this one's axis
    s0, s1 = getattr(wall, k0), getattr(wall, k1)
    n0, n1 = (c2, s1) if abs(s0 - c) < _EPS else (s0, c2)
    if abs(n1 - n0) < MIN_ROOM_M or (n1 - n0) * (s1 - s0) <= 0:
        return None
    lead = (s0 - n0) * (1.0 if s1 > s0 else -1.0)  # how much further along it its openings now start
    openings = tuple(replace(o, start=o.start + lead, end=o.end + lead) for o in wall.openings)
    moved = replace(wall, **{k0: n0, k1: n1}, openings=openings)
    if any(o.start < -_EPS or o.end > moved.length + _EPS for o in openings):
        return None
    return moved if _clear_of_openings(moved, orient, c2, t) else None


def _clear_of_openings(wall: Wall, orient: str, c2: float, t: float) -> bool:
    """Whether no opening of `wall` (across the moved one) lies near where the moved wall now meets it."""
    start, end = (wall.y0, wall.y1) if orient == "h" else (wall.x0, wall.x1)
    at = (c2 - start) * (1.0 if end > start else -1.0)
    gap = t / 2 + OPENING_CLEAR_M
    return not any(o.start - gap < at < o.end + gap for o in wall.openings)


def _footprint(o: SceneObject, dx: float = 0.0, dy: float = 0.0) -> RectPose:
    return (o.x + dx, o.y + dy, o.yaw + math.pi / 2, o.size[0], o.size[1])  # the width axis points at yaw + pi/2


def _corners(r: RectPose) -> np.ndarray:
    cx, cy, yaw, w, d = r
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[cx + c * a - s * b, cy + s * a + c * b] for a in (-w / 2, w / 2) for b in (-d / 2, d / 2)])


def _overlap(a: RectPose, b: RectPose, gap: float = 0.0) -> bool:
    """Whether two rotated rectangles come closer than `gap` (separating axes; touching is no overlap)."""
    if math.hypot(a[0] - b[0], a[1] - b[1]) > (math.hypot(a[3], a[4]) + math.hypot(b[3], b[4])) / 2 + gap:
        return False
    ca, cb = _corners(a), _corners(b)
    for yaw in (a[2], a[2] + math.pi / 2, b[2], b[2] + math.pi / 2):
        axis = np.array([math.cos(yaw), math.sin(yaw)])
        pa, pb = ca @ axis, cb @ axis
        if pa.max() + gap <= pb.min() + 1e-9 or pb.max() + gap <= pa.min() + 1e-9:
            return False
    return True


def _attached(plan: _Plan, wall: Wall, o: SceneObject) -> bool:
    """Whether `o` hangs on the wall that moves (on either face) or swings from one of its doorways."""
    v, u = (o.x, o.y - plan.line) if plan.orient == "h" else (o.y, o.x - plan.line)
    if not plan.span[0] - _EPS <= v <= plan.span[1] + _EPS:
        return False
    facing = abs(math.sin(o.yaw)) if plan.orient == "h" else abs(math.cos(o.yaw))  # its front faces across
    if o.kind in _HUNG and facing > 0.99 and abs(u) <= wall.thickness / 2 + o.size[1] / 2 + 0.03:
        return True
    if o.kind == "door":  # an open leaf standing out of the wall, hinged at a doorway's end
        base, along = (wall.x0, wall.direction[0]) if plan.orient == "h" else (wall.y0, wall.direction[1])
        return any(op.kind == "doorway" and abs(u) <= (op.end - op.start) / 2 + 0.15
                   and min(abs(v - base - along * op.start), abs(v - base - along * op.end)) < 0.06
                   for op in wall.openings)
    return False


def _apply_objects(plan: _Plan, scene: Scene, objects: list[SceneObject]) -> list[SceneObject] | None:
    """`objects` with the wall's own things moved with it and the furniture in its way pushed ahead of it or
    taken out (see above); None when a door or window is in its way."""
    wall = scene.walls[plan.move.wall]
    d, step = plan.move.distance, np.asarray(plan.step)
    out = list(objects)
    fixed = {k for k, o in enumerate(out) if _attached(plan, wall, o)}
    for k in fixed:
        out[k] = replace(out[k], x=out[k].x + step[0] * d, y=out[k].y + step[1] * d)
    swing = [k for k in sorted(fixed) if out[k].blocks_laser]  # its doors' leaves (and extinguishers)
    base, along = (wall.x0, wall.direction[0]) if plan.orient == "h" else (wall.y0, wall.direction[1])
    face = d + wall.thickness / 2  # the new face, on the side it moved to
    passages = [plan.strip(*sorted((base + along * op.start, base + along * op.end)), face, face + PASSAGE_M)
                for op in wall.openings if op.kind == "doorway"]  # in front of its doorways, where it moved to
    band = plan.band_rect()
    rooms = {r.name: r for r in plan.rooms}
    doorways = [_doorway(w, op) for w in plan.walls for op in w.openings if op.kind == "doorway"]
    was = [_footprint(o) for o in objects]  # where everything stood: what overlapped before may overlap after
    now = [_footprint(o) for o in out]
    pushed: dict[int, float] = {}
    dropped: set[int] = set()

    def swept(k: int) -> list[RectPose]:
        """Where the wall's leaves now swing (but one `out[k]` stood in already: the generator's) and, for
        furniture, the passages through its doorways."""
        return [now[j] for j in swing if not _overlap(was[k], was[j])] + (passages if out[k].blocks_laser else [])

    def need(k: int) -> float:
        """How far `out[k]` must go to clear the wall's way and what it sweeps with it (0: it is clear)."""
        fp = now[k]
        if not any(_overlap(fp, z) for z in (band, *swept(k))):
            return 0.0
        s = max(0.0, plan.band[1] - float(plan.across(_corners(fp)).min())) + 1e-4
        while any(_overlap(_footprint(out[k], *(step * s)), z) for z in swept(k)) and s < d + 1.5:
            s += 0.05
        return s

    def fits(k: int, fp: RectPose) -> bool:
        """Whether `out[k]` may stand at `fp`: in its room, clear of the wall, doorways, leaves and fixtures."""
        o = out[k]
        room = rooms.get(o.room) or rooms.get(scene.room_at(o.x, o.y)[0])
        if room is None or not _within(fp, room.rect, wall.thickness / 2 - 0.03) or _overlap(fp, band):
            return False
        if o.blocks_laser and any(_overlap(fp, z) for z in (*doorways, *swept(k))):
            return False
        return o.kind not in _HUNG or not any(
            _overlap(fp, now[j], 0.05) and not _overlap(was[k], was[j], 0.05)
            for j, other in enumerate(out) if j != k and j not in dropped and other.kind in _HUNG)

    def push(k: int, s: float, chain: frozenset) -> dict[int, float] | None:
        """`out[k]` pushed by `s` and, in turn, what it would run into (by as much, or by what that needs
        itself); None when any of them does not fit."""
        fp = _footprint(out[k], *(step * s))
        if not fits(k, fp):
            return None
        moves = {k: s}
        if not out[k].blocks_laser:
            return moves
        for j, o in enumerate(out):
            if j == k or j in chain or j in moves or j in fixed or j in dropped or not o.blocks_laser or \
                    o.kind == "clutter" or not _overlap(fp, now[j]) or _overlap(was[k], was[j]):
                continue
            if j in pushed or o.kind in _NEVER_PUSHED:
                return None
            sub = push(j, max(s, need(j)), chain | moves.keys())
            if sub is None:
                return None
            moves.update(sub)
        return moves

    for k, o in enumerate(out):  # what the wall runs into, in order; what cannot move out of its way goes
        if k in fixed or k in pushed or k in dropped or o.kind == "clutter" or not (s := need(k)):
            continue
        if o.kind in _NEVER_PUSHED:
            return None
        moves = push(k, s, frozenset())
        if moves is None:
            dropped.add(k)
            continue
        for j, sj in moves.items():
            pushed[j], now[j] = sj, _footprint(out[j], *(step * sj))
    for j, o in enumerate(out):  # what stands on a desk goes with it
        if o.kind == "clutter":
            desk = next((k for k in (*pushed, *dropped) if out[k].kind == "desk" and _on(out[k], o)), None)
            if desk in dropped:
                dropped.add(j)
            elif desk is not None:
                pushed[j] = pushed[desk]
    return [replace(o, x=o.x + step[0] * pushed[k], y=o.y + step[1] * pushed[k]) if k in pushed else o
            for k, o in enumerate(out) if k not in dropped]


def _apply_lights(plan: _Plan, lights: list[Light]) -> list[Light]:
    """Ceiling lights in the wall's way, moved just past it."""
    step, out = np.asarray(plan.step), []
    band = plan.band_rect()
    for lt in lights:
        u = float(plan.across(np.array([[lt.x, lt.y]]))[0])
        if _overlap(band, (lt.x, lt.y, 0.0, 0.0, 0.0)):
            s = plan.band[1] - u + 1e-4
            lt = replace(lt, x=lt.x + step[0] * s, y=lt.y + step[1] * s)
        out.append(lt)
    return out


def _on(desk: SceneObject, o: SceneObject) -> bool:
    """Whether `o` stands on `desk` (its centre over the desk's top)."""
    c, s = math.cos(desk.yaw + math.pi / 2), math.sin(desk.yaw + math.pi / 2)
    a, b = c * (o.x - desk.x) + s * (o.y - desk.y), -s * (o.x - desk.x) + c * (o.y - desk.y)
    return abs(a) <= desk.size[0] / 2 + 1e-6 and abs(b) <= desk.size[1] / 2 + 1e-6 and o.z >= desk.size[2] - 0.05


def _within(fp: RectPose, rect: Rect, margin: float) -> bool:
    pts = _corners(fp)
    return bool(np.all(rect.contains(pts[:, 0], pts[:, 1], margin=margin)))


def _doorway(wall: Wall, op: Opening) -> RectPose:
    """The passage through a doorway: its width, `DOORWAY_CLEAR_M` deep on both sides of the wall."""
    dx, dy = wall.direction
    mid = (op.start + op.end) / 2
    return (wall.x0 + dx * mid, wall.y0 + dy * mid, math.atan2(dy, dx), op.end - op.start,
            wall.thickness + 2 * DOORWAY_CLEAR_M)


def move_wall(scene: Scene, seed: int, distance: float, areas: tuple[str, ...],
              objects: list[SceneObject]) -> tuple[list[SceneObject], dict]:
    """(`objects` after one interior wall moved `distance` metres, the scene fields that change: walls, rooms,
    lights); ValueError when no wall (of `areas`, if given) can move that far."""
    plan = _choose(scene, seed, distance, areas)
    if plan is None:
        raise ValueError(f"no interior wall {'of ' + ', '.join(areas) + ' ' if areas else ''}can move by "
                         f"{distance} m without closing a door or squeezing a room")
    applied = _apply_objects(plan, scene, objects)
    if applied is None:  # only doors and windows stop a wall, and the change above moves neither
        raise RuntimeError(f"the wall of {', '.join(plan.move.rooms)} ran into a door after the change")
    return applied, {"walls": plan.walls, "rooms": plan.rooms, "lights": _apply_lights(plan, scene.lights)}
