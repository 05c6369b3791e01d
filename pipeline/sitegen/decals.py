"""Meshes of the identity cues: signage panels with their drawn faces, desk clutter, window outside views.

These are made here rather than taken from the asset library: a plate or a board is a thin box with a
picture on its front, and clutter is a handful of boxes, so generating them is exact and costs nothing.
`SiteTextures` gives each object the picture it shows (a poster's pool picture, a plate's number, a
board's notes, an escape plan of this floor), cached so that equal keys share one texture.
"""

from __future__ import annotations

import numpy as np

from pipeline.sitegen import pictures, signage
from pipeline.sitegen.asset_types import MeshPart, Model
from pipeline.sitegen.procedural_assets import CREATOR, SOURCE, _Builder
from pipeline.sitegen.scene import Scene, SceneObject

FRAMES = {"plate": (0.55, 0.55, 0.57), "notice_board": (0.45, 0.30, 0.15), "escape_plan": (0.9, 0.9, 0.9),
          "sign": (0.2, 0.2, 0.22)}
OUTSIDE_M = (12.0, 3.0)  # the outside view image spans this many metres along the facade, and up
DAYLIGHT = 0.85  # emissive share of an outside view: daylight does not depend on the room's lamps


class SiteTextures:
    """Pictures shown by the site's objects; `unique` posters draw from the site's unbounded pool, otherwise
    from the library's few photographs (repeating)."""

    def __init__(self, scene: Scene, photos: list[np.ndarray], unique: bool):
        self.scene, self.photos, self.unique = scene, list(photos), unique
        self._cache: dict[str, np.ndarray] = {}

    def _get(self, key: str, make) -> np.ndarray:
        if key not in self._cache:
            self._cache[key] = np.ascontiguousarray(make())
        return self._cache[key]

    def poster(self, index: int) -> np.ndarray:
        if not self.unique:
            return self.photos[index % len(self.photos)]
        return self._get(f"picture:{index}", lambda: pictures.picture(index, self.scene.seed, self.photos))

    def signage(self, obj: SceneObject) -> np.ndarray:
        label, seed = obj.label, self.scene.seed
        if obj.kind == "plate":
            number, _, name = label.partition("|")
            wing = self.scene.wing_at(obj.x, obj.y)
            return self._get(label, lambda: signage.plate_image(number, name, wing.colour if wing else (0.4,) * 3))
        if obj.kind == "notice_board":
            return self._get(label, lambda: signage.board_image(seed, label))
        if obj.kind == "escape_plan":
            _, x, y, _yaw = label.split(":")
            return self._get(label, lambda: signage.plan_image(self.scene, (float(x), float(y)), float(_yaw)))
        if obj.kind == "sign":
            lines = [(t[:-2], t[-1]) for t in label.split(":")[1:]]
            wing = self.scene.wing_at(obj.x, obj.y)
            return self._get(f"{label}@{wing.letter if wing else ''}",
                             lambda: signage.sign_image(lines, wing.colour if wing else (0.3, 0.3, 0.3)))
        raise ValueError(f"object {obj.instance_id} ({obj.kind}) shows no signage")

    def outside(self, facade: int) -> np.ndarray:
        return self._get(f"outside:{facade}", lambda: signage.outside_view(facade, self.scene.seed))


def signage_model(obj: SceneObject, face: np.ndarray) -> Model:
    """A panel of the object's size: a frame box, the drawn face 2 mm in front of it (front = -y)."""
    w, d, h = obj.size
    b = _Builder()
    b.box((-w / 2, -d / 2 + 0.002, 0), (w / 2, d / 2, h), FRAMES[obj.kind])
    m = min(w, h) * 0.04 if obj.kind in ("notice_board", "escape_plan") else 0.0
    y = -d / 2
    b.quad([(-w / 2 + m, y, m), (w / 2 - m, y, m), (w / 2 - m, y, h - m), (-w / 2 + m, y, h - m)], (0, -1, 0),
           (1.0, 1.0, 1.0), texture=face, role="picture")
    return _finish(b, obj.kind)


def clutter_model(variant: int) -> Model:
    """A monitor on a stand, a keyboard, a pile of books and papers, in an arrangement the variant draws."""
    rng = np.random.default_rng(variant)
    b = _Builder()
    w, d = 0.9, 0.4
    mx = rng.uniform(-0.2, 0.2)
    if rng.random() < 0.85:  # monitor: stand, screen (front -y: facing the chair)
        b.box((mx - 0.04, 0.05, 0), (mx + 0.04, 0.1, 0.12), (0.15, 0.15, 0.15))
        sw = rng.uniform(0.45, 0.6)
        b.box((mx - sw / 2, 0.02, 0.1), (mx + sw / 2, 0.06, 0.1 + sw * 0.6), (0.08, 0.08, 0.09))
        b.box((mx - sw / 2 + 0.015, 0.017, 0.115), (mx + sw / 2 - 0.015, 0.02, 0.085 + sw * 0.6),
              tuple(rng.uniform(0.1, 0.5, 3)))  # the lit screen's colour
        b.box((mx - 0.22, -0.18, 0), (mx + 0.22, -0.04, 0.02), (0.2, 0.2, 0.2))  # keyboard
    side = -0.38 if mx > 0 else 0.22
    z = 0.0
    for _ in range(int(rng.integers(0, 5))):  # books
        t = rng.uniform(0.02, 0.05)
        bw, bd = rng.uniform(0.15, 0.22), rng.uniform(0.2, 0.28)
        b.box((side, -0.1, z), (side + bw, -0.1 + bd, z + t), tuple(rng.uniform(0.1, 0.9, 3)))
        z += t
    if rng.random() < 0.6:  # papers
        px = rng.uniform(-0.4, 0.2)
        b.box((px, -0.18, 0), (px + 0.21, 0.08, 0.004), (0.95, 0.95, 0.93))
    b.box((-w / 2, -d / 2, 0), (-w / 2 + 0.001, -d / 2 + 0.001, 0.001), (0.5, 0.5, 0.5))  # fixes the footprint
    b.box((w / 2 - 0.001, d / 2 - 0.001, 0), (w / 2, d / 2, 0.001), (0.5, 0.5, 0.5))
    return _finish(b, "clutter")


def _finish(b: _Builder, kind: str) -> Model:
    parts, _ = b.parts()
    pos = np.concatenate([p.positions for p in parts])
    size = tuple(float(v) for v in pos.max(axis=0) - pos.min(axis=0))
    return Model(key=f"siteloc/{kind}", cls="", name=kind, creator=CREATOR, license="CC0-1.0", source=SOURCE,
                 size=size, parts=parts, procedural=True, kind=kind)  # type: ignore[arg-type]


def outside_part(obj: SceneObject, part: MeshPart, positions_map: np.ndarray, scene: Scene,
                 textures: SiteTextures) -> tuple[np.ndarray, np.ndarray]:
    """The texture and map-anchored uvs of a window pane, so it shows its facade's outside view."""
    b = scene.bounds
    dist = {0: obj.y - b.y0, 1: b.x1 - obj.x, 2: b.y1 - obj.y, 3: obj.x - b.x0}  # south, east, north, west
    facade = min(dist, key=dist.get)  # type: ignore[arg-type]
    along = positions_map[:, 0] if facade in (0, 2) else positions_map[:, 1]
    if facade in (0, 3):
        along = -along  # seen from inside, the view runs the other way round the building
    u = along / OUTSIDE_M[0]
    v = (positions_map[:, 2] - 0.6) / OUTSIDE_M[1]
    return textures.outside(facade), np.stack([u, v], axis=1).astype(np.float32)


def is_pane(obj: SceneObject, part: MeshPart) -> bool:
    return obj.cls == "window" and part.opacity < 0.95
