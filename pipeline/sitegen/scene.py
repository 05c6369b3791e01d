"""Scene description of a reference site: floor plan, walls with openings, rooms with areas, and objects.

Everything is in the map frame (ROS map_server: x right, y up, metres, yaw counter-clockwise) with z up
from the floor. The plan is a grid of corridors (every corridor line spans the whole grid, so corridors
form loops) with a band of rooms along the outer walls and rows of rooms facing the corridors inside
the blocks between them. Rooms repeat a few standard sizes and furnishings, doors and windows repeat
along the corridors, and the layout is mirror-symmetric up to small random jitter: hard in the way real
office floors are hard. The same preset and seed always give the same scene (`site_scene.build_scene`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Rect:
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def w(self) -> float:
        return self.x1 - self.x0

    @property
    def h(self) -> float:
        return self.y1 - self.y0

    @property
    def cx(self) -> float:
        return 0.5 * (self.x0 + self.x1)

    @property
    def cy(self) -> float:
        return 0.5 * (self.y0 + self.y1)

    def contains(self, x, y, margin: float = 0.0):
        return (x >= self.x0 + margin) & (x <= self.x1 - margin) & (y >= self.y0 + margin) & (y <= self.y1 - margin)


@dataclass(frozen=True)
class Opening:
    """A gap in a wall: `start`..`end` metres along the wall from (x0, y0), from z0 to z1.

    `kind` is "doorway" (open passage, free in the map), "door" (a closed door fills it: occupied in the
    map) or "window" (above the laser plane: the wall stays occupied in the map).
    """

    start: float
    end: float
    z0: float
    z1: float
    kind: str


@dataclass(frozen=True)
class Wall:
    """A straight wall of `thickness` centred on the segment (x0, y0) -> (x1, y1), from the floor to `height`."""

    x0: float
    y0: float
    x1: float
    y1: float
    thickness: float
    height: float
    material: int  # index into the site's wall textures
    exterior: bool = False
    openings: tuple[Opening, ...] = ()

    @property
    def length(self) -> float:
        return float(np.hypot(self.x1 - self.x0, self.y1 - self.y0))

    @property
    def direction(self) -> tuple[float, float]:
        n = self.length
        return (self.x1 - self.x0) / n, (self.y1 - self.y0) / n


@dataclass(frozen=True)
class Room:
    """A named region of free space; `areas` split it into labelled parts (second paper's (room, area))."""

    name: str
    kind: str  # "office", "meeting", "corridor", "lobby"
    rect: Rect
    areas: tuple[tuple[str, Rect], ...]
    floor_material: int
    door_side: str = ""  # which side faces the corridor: "north", "south", "east", "west"


@dataclass(frozen=True)
class SceneObject:
    """One placed object. `cls` is a detector class, or "" for furniture that is not detected (desks...).

    (x, y) is the footprint centre in the map frame, z the height of its base, yaw the heading of its
    front (the model's front faces its local -y, as in Sweet Home 3D's plan view, rotated by yaw).
    `variant` picks one of the asset library's models of the class; `size` is (width, depth, height).
    `blocks_laser` marks objects solid at the laser's height (they are drawn into the map).
    """

    instance_id: int
    cls: str
    kind: str  # finer name: "desk", "chair", "door_closed", "door_open", "poster", ...
    x: float
    y: float
    z: float
    yaw: float
    size: tuple[float, float, float]
    variant: int
    blocks_laser: bool
    room: str
    texture: int = -1  # e.g. which poster picture; -1 = the model's own
    label: str = ""  # what signage shows: a plate's "A104|Dr. M. Weber", a board's key (see sitegen.signage)


@dataclass(frozen=True)
class Light:
    x: float
    y: float
    z: float
    intensity: float


@dataclass(frozen=True)
class Wing:
    """A zone of the floor with its own letter (room numbers) and colour scheme (paint, floors, signs)."""

    letter: str
    rect: Rect
    colour: tuple[float, float, float]
    floor_material: int


@dataclass
class Scene:
    name: str
    seed: int
    bounds: Rect  # the building's outer wall rectangle
    walls: list[Wall]
    rooms: list[Room]
    objects: list[SceneObject]
    lights: list[Light]
    wall_height: float
    classes: tuple[str, ...]
    closed: list[Rect] = field(default_factory=list)  # regions nobody enters (service cores): unknown in the map
    wings: list[Wing] = field(default_factory=list)  # identity zones (`sitegen.identity`); empty: one plain floor
    paint: dict[str, tuple[float, float, float]] = field(default_factory=dict)  # room name -> its walls' tint
    outside_views: bool = False  # window panes show the facade's outside view instead of flat glass
    painted: bool = False  # walls in smooth paint (`identity.surface_bands`) instead of the library's textures
    dado_height: float = 0.0  # painted corridors: the wing-coloured band from the floor up to this height, m

    def wing_at(self, x: float, y: float) -> Wing | None:
        for wing in self.wings:
            if wing.rect.contains(x, y):
                return wing
        return min(self.wings, key=lambda w: (w.rect.cx - x) ** 2 + (w.rect.cy - y) ** 2) if self.wings else None

    def objects_of(self, cls: str) -> list[SceneObject]:
        return [o for o in self.objects if o.cls == cls]

    def room_at(self, x: float, y: float) -> tuple[str, str]:
        """(room, area) labels of a point; ("", "") outside every room."""
        for room in self.rooms:
            if room.rect.contains(x, y):
                for area, rect in room.areas:
                    if rect.contains(x, y):
                        return room.name, area
                return room.name, room.areas[0][0]
        return "", ""

    def class_counts(self) -> dict[str, int]:
        return {c: sum(o.cls == c for o in self.objects) for c in self.classes}
