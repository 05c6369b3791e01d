"""Hand-built scenes for the laser and trajectory tests: small, with every case written out in metres.

`small_floor` (12 x 8 m, walls 0.2 m thick centred on their lines, so wall faces fall on 5 cm cell
boundaries of a map whose origin is (-1, -1)):

    y=8 +-------------------+-------------------+
        |                   |        cabinet  ##|  <- closed core x 10..12, y 6..8 (a cabinet inside)
        |   desk (yaw 0.3)  |                 ##|
        |   chair           |                   |
        |     room A        |     room B        |
    y=3 +----[ ]------------+---[ ]-----[door]--+     doorways x 2..3 and 7..8, closed door x 10..11
        |  corridor                     plant   |
    y=0 +------------[window]-----[ext door]----+     window x 4..5.2, exterior door x 9..10.6
        x=0                 x=6                 x=12
"""

from __future__ import annotations

from pipeline.sitegen.scene import Opening, Rect, Room, Scene, SceneObject, Wall

T = 0.2  # wall thickness


def _wall(x0, y0, x1, y1, *openings, exterior=False) -> Wall:
    return Wall(x0, y0, x1, y1, T, 2.5, 0, exterior, tuple(openings))


def _obj(i: int, kind: str, x: float, y: float, yaw: float, size, blocks: bool, room: str) -> SceneObject:
    return SceneObject(i, "", kind, x, y, 0.0, yaw, size, 0, blocks, room)


DESK = _obj(1, "desk", 3.0, 6.6, 0.3, (1.4, 0.7, 0.75), True, "A")
CHAIR = _obj(2, "chair", 3.0, 5.6, 0.0, (0.5, 0.52, 0.9), True, "A")
CABINET = _obj(3, "cabinet", 8.0, 7.5, 0.0, (0.8, 0.45, 1.2), True, "B")
PLANT = _obj(4, "plant", 11.0, 1.5, 0.0, (0.5, 0.5, 1.2), True, "corridor")
POSTER = _obj(5, "poster", 5.0, 0.13, 1.5708, (0.6, 0.03, 0.85), False, "corridor")
CORE_CABINET = _obj(6, "cabinet", 11.0, 7.0, 0.0, (0.8, 0.45, 1.2), True, "")


def small_floor() -> Scene:
    walls = [
        _wall(0, 0, 12, 0, Opening(4.0, 5.2, 0.9, 2.1, "window"), Opening(9.0, 10.6, 0.0, 2.1, "door"), exterior=True),
        _wall(12, 0, 12, 8, exterior=True),
        _wall(12, 8, 0, 8, exterior=True),
        _wall(0, 8, 0, 0, exterior=True),
        _wall(0, 3, 12, 3, Opening(2.0, 3.0, 0, 2.1, "doorway"), Opening(7.0, 8.0, 0, 2.1, "doorway"),
              Opening(10.0, 11.0, 0, 2.1, "door")),
        _wall(6, 3, 6, 8),
        _wall(10, 6, 12, 6),
        _wall(10, 6, 10, 8),
    ]
    rooms = [
        Room("corridor", "corridor", Rect(0, 0, 12, 3), (("s0", Rect(0, 0, 12, 3)),), 0),
        Room("A", "office", Rect(0, 3, 6, 8), (("a0", Rect(0, 3, 6, 8)),), 0, "south"),
        Room("B", "office", Rect(6, 3, 12, 8), (("b0", Rect(6, 3, 12, 8)),), 0, "south"),
    ]
    objects = [DESK, CHAIR, CABINET, PLANT, POSTER, CORE_CABINET]
    return Scene("small", 0, Rect(0, 0, 12, 8), walls, rooms, objects, [], 2.5, (), closed=[Rect(10, 6, 12, 8)])


def box_room(w: float = 6.0, h: float = 4.0, doorway: tuple[float, float] | None = None) -> Scene:
    """An empty w x h room; inner wall faces at 0.1 m from its outline. `doorway`: (start, end) along
    the east wall (x = w), an opening to the outside."""
    east = (Opening(doorway[0], doorway[1], 0.0, 2.1, "doorway"),) if doorway else ()
    walls = [_wall(0, 0, w, 0), _wall(w, 0, w, h, *east), _wall(w, h, 0, h), _wall(0, h, 0, 0)]
    room = Room("room", "office", Rect(0, 0, w, h), (("r0", Rect(0, 0, w, h)),), 0)
    return Scene("box", 0, Rect(0, 0, w, h), walls, [room], [], [], 2.5, ())
