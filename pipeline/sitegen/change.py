"""Environment change: the same building some months later (the case of a team retraining after a change).

Walls, doors and windows stay, and so do room plates, escape plans and signs; furniture moves (chairs and
bins shift), posters are replaced or taken down and new ones hung, notice boards get new notes, some
plants go, and the lighting differs (a global
exposure and tint shift applied by the renderer). Everything is seeded, so the changed site is
reproducible too. With `ChangeSpec.move_wall_m`, one interior wall moves as well (`choose_wall_move`): the
occupancy map, the laser's world and the meshes, all drawn from the scene's walls, then differ around it
(pipeline.sitegen.wall_move).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from pipeline.sitegen.identity import SIGNAGE_KINDS
from pipeline.sitegen.scene import Scene, SceneObject

MOVABLE = {"chair", "trash_bin", "plant"}


@dataclass(frozen=True)
class ChangeSpec:
    move_share: float = 0.6  # movable objects that move
    move_m: tuple[float, float] = (0.2, 0.9)  # how far
    poster_replace_share: float = 0.5
    poster_remove_share: float = 0.15
    plant_remove_share: float = 0.3
    board_update_share: float = 0.7  # notice boards whose notes are replaced
    exposure_gain: float = 0.85  # the changed site's lighting is dimmer and warmer
    tint: tuple[float, float, float] = (1.05, 1.0, 0.9)
    move_wall_m: float = 0.0  # > 0: one interior wall moves this far (`choose_wall_move`); 0: the walls stay


def area_keys(scene: Scene) -> set[str]:
    """Every `room` and `room/area` label of the scene (what `areas` may name)."""
    return {r.name for r in scene.rooms} | {f"{r.name}/{a}" for r in scene.rooms for a, _ in r.areas}


def in_areas(scene: Scene, x: float, y: float, areas: tuple[str, ...]) -> bool:
    """Whether a point lies in one of `areas` (room names or room/area labels); every point when it is empty."""
    if not areas:
        return True
    room, area = scene.room_at(x, y)
    return room in areas or f"{room}/{area}" in areas


def change_scene(scene: Scene, seed: int, spec: ChangeSpec = ChangeSpec(), poster_pictures: int = 12,
                 unique_pictures: bool = False, areas: tuple[str, ...] = ()) -> Scene:
    """A changed copy of `scene`: moved furniture, new and removed posters, fewer plants, notice boards
    with new notes. Room plates, escape plans and signs stay, as they do in buildings. With
    `unique_pictures`, a replaced or new poster shows a picture the site never showed (the pool's next).
    With `areas` (room names or room/area labels), only objects standing in them change. With
    `spec.move_wall_m`, an interior wall moves too (with `areas`, one beside their rooms; see `choose_wall_move`);
    ValueError when none can.

    Instance ids are renumbered densely; the returned scene's `name` gains a `-changed` suffix.
    """
    unknown = sorted(set(areas) - area_keys(scene))
    if unknown:
        raise ValueError(f"no area {unknown} in the site; its areas are {', '.join(sorted(area_keys(scene)))}")
    rng = np.random.default_rng(seed + 104729)
    fresh = iter(range(sum(o.cls == "poster" for o in scene.objects), 1 << 30))

    def new_picture() -> int:
        return next(fresh) if unique_pictures else int(rng.integers(0, poster_pictures))

    kept: list[SceneObject] = []
    for obj in scene.objects:
        if not in_areas(scene, obj.x, obj.y, areas):
            kept.append(obj)
            continue
        if obj.kind == "notice_board" and rng.random() < spec.board_update_share:
            obj = replace(obj, label=obj.label.rsplit(":", 1)[0] + ":v1")  # the notes are new ones

        if obj.cls == "plant" and rng.random() < spec.plant_remove_share:
            continue
        if obj.cls == "poster":
            u = rng.random()
            if u < spec.poster_remove_share:
                continue
            if u < spec.poster_remove_share + spec.poster_replace_share:
                obj = replace(obj, texture=new_picture())
        elif obj.cls in MOVABLE and rng.random() < spec.move_share:
            angle = rng.uniform(-math.pi, math.pi)
            dist = rng.uniform(*spec.move_m)
            candidate = replace(obj, x=obj.x + dist * math.cos(angle), y=obj.y + dist * math.sin(angle),
                                yaw=obj.yaw + rng.normal(0, 0.6))
            # Only moves that stay inside the object's room and clear of walls are taken.
            room = next((r for r in scene.rooms if r.name == obj.room), None)
            if room is not None and room.rect.contains(candidate.x, candidate.y, margin=0.45):
                obj = candidate
        kept.append(obj)
    # New posters on corridor walls: copies of existing posters slid along their wall with new pictures.
    posters = [o for o in kept if o.cls == "poster" and o.room.startswith("corridor") and
               in_areas(scene, o.x, o.y, areas)]
    for obj in rng.permutation(len(posters))[: max(1, len(posters) // 5)] if posters else []:
        src = posters[int(obj)]
        dx, dy = -math.sin(src.yaw), math.cos(src.yaw)
        for _ in range(4):  # a few tries; a spot that would cover a door, a window or a poster is skipped
            along = rng.uniform(0.8, 1.6) * rng.choice([-1, 1])
            new = replace(src, x=src.x + along * dx, y=src.y + along * dy,
                          texture=new_picture())
            if not any(_overlaps(new, o) for o in kept if o.cls in ("door", "window", "poster", "exit_sign",
                                                                      "fire_extinguisher") or o.kind in SIGNAGE_KINDS):
                kept.append(new)
                break
    moved = {}
    if spec.move_wall_m > 0:  # its own random stream: the draws above are the same with or without it
        from pipeline.sitegen.wall_move import move_wall

        kept, moved = move_wall(scene, seed, spec.move_wall_m, areas, kept)
    objects = [replace(o, instance_id=i + 1) for i, o in enumerate(kept)]
    return replace(scene, name=f"{scene.name}-changed", objects=objects, **moved)


def _overlaps(a: SceneObject, b: SceneObject, gap: float = 0.1) -> bool:
    """Whether two wall-mounted things would touch: closer than half their widths plus a gap."""
    return math.hypot(a.x - b.x, a.y - b.y) < (a.size[0] + b.size[0]) / 2 + gap
