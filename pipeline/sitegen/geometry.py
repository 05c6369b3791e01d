"""Scene -> triangle meshes for the renderer: walls with their openings cut out, floors, ceiling, objects.

Structure gets instance id 0; every object gets its own id (undetected furniture too, so it occludes
correctly in the id buffer and nothing but its pixels carries its id). Surfaces of the same texture are
merged into one mesh, which keeps the draw calls few on a CPU rasteriser. UVs of walls, floors and
ceilings are in metres divided by a tile size, so photographic textures repeat at a realistic scale.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from pipeline.sitegen.decals import DAYLIGHT, SiteTextures, clutter_model, is_pane, outside_part, signage_model
from pipeline.sitegen.identity import SIGNAGE_KINDS
from pipeline.sitegen.render import RenderMesh
from pipeline.sitegen.scene import Rect, Scene, SceneObject, Wall

TILE_M = {"wall": 1.6, "floor": 1.2, "ceiling": 1.2}


def _quad(p0, p1, p2, p3, normal, uv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two triangles of the quad p0 p1 p2 p3 (counter-clockwise), one normal, uvs per corner."""
    pos = np.array([p0, p1, p2, p0, p2, p3], dtype=np.float32)
    nrm = np.repeat(np.array([normal], dtype=np.float32), 6, axis=0)
    uvs = np.array([uv[0], uv[1], uv[2], uv[0], uv[2], uv[3]], dtype=np.float32)
    return pos, nrm, uvs


def _box_faces(wall: Wall, a0: float, a1: float, z0: float, z1: float, tile: float = TILE_M["wall"]):
    """The six faces of the wall piece from a0..a1 along the wall and z0..z1 high, uvs in `tile` metres."""
    dx, dy = wall.direction
    nx, ny = -dy, dx
    t = wall.thickness / 2
    faces = []
    for sign in (1.0, -1.0):  # both long faces
        ox, oy = nx * t * sign, ny * t * sign
        c = [(wall.x0 + dx * a + ox, wall.y0 + dy * a + oy) for a in (a0, a1)]
        uv = [(a0 / tile, z0 / tile), (a1 / tile, z0 / tile), (a1 / tile, z1 / tile), (a0 / tile, z1 / tile)]
        faces.append(_quad((*c[0], z0), (*c[1], z0), (*c[1], z1), (*c[0], z1), (nx * sign, ny * sign, 0.0), uv))
    for a, sign in ((a0, -1.0), (a1, 1.0)):  # the two ends (door jambs)
        p = (wall.x0 + dx * a, wall.y0 + dy * a)
        c0 = (p[0] + nx * t, p[1] + ny * t)
        c1 = (p[0] - nx * t, p[1] - ny * t)
        uv = [(0, z0 / tile), (2 * t / tile, z0 / tile), (2 * t / tile, z1 / tile), (0, z1 / tile)]
        faces.append(_quad((*c0, z0), (*c1, z0), (*c1, z1), (*c0, z1), (dx * sign, dy * sign, 0.0), uv))
    for z, sign in ((z1, 1.0), (z0, -1.0)):  # top and bottom (lintels, sills)
        ends = ((a0, 1), (a1, 1), (a1, -1), (a0, -1))
        c = [(wall.x0 + dx * a + nx * t * s, wall.y0 + dy * a + ny * t * s) for a, s in ends]
        uv = [(a0 / tile, 0), (a1 / tile, 0), (a1 / tile, 2 * t / tile), (a0 / tile, 2 * t / tile)]
        faces.append(_quad(*[(x, y, z) for x, y in c], (0.0, 0.0, sign), uv))
    return faces


def wall_pieces(wall: Wall) -> list[tuple[float, float, float, float]]:
    """(a0, a1, z0, z1) solid pieces of a wall once its openings are cut out."""
    pieces = []
    cursor = 0.0
    for o in sorted(wall.openings, key=lambda o: o.start):
        if o.start > cursor + 1e-6:
            pieces.append((cursor, o.start, 0.0, wall.height))
        if o.z0 > 1e-6:
            pieces.append((o.start, o.end, 0.0, o.z0))
        if o.z1 < wall.height - 1e-6:
            pieces.append((o.start, o.end, o.z1, wall.height))
        cursor = max(cursor, o.end)
    if wall.length > cursor + 1e-6:
        pieces.append((cursor, wall.length, 0.0, wall.height))
    return pieces


def _concat(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))  # type: ignore[return-value]


def _tile(library, role: str, index: int) -> float:
    """The real repeat size of a texture (the catalog's), else a typical one for its role."""
    infos = getattr(library, "texture_info", {}).get(role) or []
    if infos:
        size = infos[index % len(infos)].tile_size_m
        if size:
            return float(max(size))
    return TILE_M[role]


PAINT_PIECE_M = 2.0  # walls are cut in pieces this long at most, so each face takes the paint of where it faces


def structure_meshes(scene: Scene, library) -> list[RenderMesh]:
    """Walls (per wall texture), floors (per floor texture) and the ceiling. With wings (`sitegen.identity`)
    each wall face is tinted by the room or wing it faces and corridor floors take their wing's material."""
    from pipeline.sitegen.identity import PAINT, floor_tint, paint_texture, surface_bands

    textures = library.textures
    out = []
    by_material: dict[tuple, list] = defaultdict(list)
    wall_tex = textures["wall"]
    for wall in scene.walls:
        tile = _tile(library, "wall", wall.material % len(wall_tex))  # one repeat size per wall, whatever it wears
        dx, dy = wall.direction
        for a0, a1, z0, z1 in wall_pieces(wall):
            if not scene.wings and not scene.painted:
                by_material[(wall.material, (1.0, 1.0, 1.0))].extend(_box_faces(wall, a0, a1, z0, z1, tile))
                continue
            n = max(1, math.ceil((a1 - a0) / PAINT_PIECE_M))
            for k in range(n):
                b0, b1 = a0 + (a1 - a0) * k / n, a0 + (a1 - a0) * (k + 1) / n
                faces = _box_faces(wall, b0, b1, z0, z1, tile)
                mx, my = wall.x0 + dx * (b0 + b1) / 2, wall.y0 + dy * (b0 + b1) / 2
                for f, face in enumerate(faces):
                    nx, ny = face[1][0][:2]
                    probe = 0.3 if f < 2 else 0.05  # long faces look 0.3 m ahead; jambs and sills just off
                    bands = surface_bands(scene, mx + nx * probe, my + ny * probe, len(wall_tex))
                    if len(bands) == 1 or f >= 4:  # one surface, or a lintel's / sill's face at its height
                        z = z1 if f == 4 else z0
                        _, material, colour = next(b for b in bands if b[0] > z + 1e-6 or b is bands[-1])
                        by_material[(material, colour)].append(face)
                        continue
                    lo = z0  # a vertical face crossing bands (a dado) is cut at each band's top
                    for top, material, colour in bands:
                        if min(top, z1) > lo + 1e-6:
                            by_material[(material, colour)].append(_box_faces(wall, b0, b1, lo, min(top, z1), tile)[f])
                        lo = max(lo, top)
    paint = paint_texture() if any(material == PAINT for material, _ in by_material) else None
    for (material, colour), faces in sorted(by_material.items()):
        pos, nrm, uv = _concat(faces)
        out.append(RenderMesh(pos, nrm, uv, paint if material == PAINT else wall_tex[material % len(wall_tex)], colour))
    floors: dict[tuple, list] = defaultdict(list)
    for room in scene.rooms:
        pieces = [(room.rect, room.floor_material)]
        if scene.wings and room.kind == "corridor":  # a corridor crossing wings changes floor where they meet
            pieces = [(c, w.floor_material) for w in scene.wings if (c := _clip(room.rect, w.rect)) is not None]
        for r, material in pieces:
            tile = _tile(library, "floor", material % len(textures["floor"]))
            uv = [(x / tile, y / tile) for x, y in ((r.x0, r.y0), (r.x1, r.y0), (r.x1, r.y1), (r.x0, r.y1))]
            tint = floor_tint(scene, r.cx, r.cy) if scene.wings and room.kind == "corridor" else (1.0, 1.0, 1.0)
            floors[(material, tint)].append(
                _quad((r.x0, r.y0, 0.0), (r.x1, r.y0, 0.0), (r.x1, r.y1, 0.0), (r.x0, r.y1, 0.0), (0, 0, 1), uv))
    floor_tex = textures["floor"]
    for (material, tint), faces in sorted(floors.items()):
        pos, nrm, uv = _concat(faces)
        out.append(RenderMesh(pos, nrm, uv, floor_tex[material % len(floor_tex)], tint))
    b, h, tile = scene.bounds, scene.wall_height, _tile(library, "ceiling", 0)
    uv = [(x / tile, y / tile) for x, y in ((b.x0, b.y0), (b.x1, b.y0), (b.x1, b.y1), (b.x0, b.y1))]
    pos, nrm, uvs = _quad((b.x0, b.y0, h), (b.x1, b.y0, h), (b.x1, b.y1, h), (b.x0, b.y1, h), (0, 0, -1), uv)
    out.append(RenderMesh(pos, nrm, uvs, textures["ceiling"][0], (1.0, 1.0, 1.0)))
    return out


def _clip(a: Rect, b: Rect) -> Rect | None:
    r = Rect(max(a.x0, b.x0), max(a.y0, b.y0), min(a.x1, b.x1), min(a.y1, b.y1))
    return r if r.w > 1e-6 and r.h > 1e-6 else None


def map_from_object(obj: SceneObject, model_size: tuple[float, float, float]) -> np.ndarray:
    """4x4 transform of a model (front -y, origin at the floor centre of its footprint) to its place."""
    sx, sy, sz = (s / max(m, 1e-6) for s, m in zip(obj.size, model_size, strict=True))
    rot = obj.yaw + math.pi / 2  # the model's front (-y, heading -pi/2) turned to face `yaw`
    c, s = math.cos(rot), math.sin(rot)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([sx, sy, sz])
    m[:3, 3] = (obj.x, obj.y, obj.z)
    return m


def object_meshes(scene: Scene, library, textures: SiteTextures) -> list[RenderMesh]:
    """Each object's model parts placed in the map frame, with the object's instance id; posters show their
    picture, signage its drawn face, and window panes the outside view when the scene has one."""
    out = []
    clutter: dict[int, object] = {}
    for obj in scene.objects:
        if obj.kind in SIGNAGE_KINDS:
            model = signage_model(obj, textures.signage(obj))
        elif obj.kind == "clutter":
            model = clutter.setdefault(obj.variant, clutter_model(obj.variant))
        else:
            model = library.model_for(obj.cls, obj.kind, obj.variant)
        m = map_from_object(obj, model.size)
        normal_m = np.linalg.inv(m[:3, :3]).T
        for part in model.parts:
            pos = part.positions @ m[:3, :3].T + m[:3, 3]
            nrm = part.normals @ normal_m.T
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
            texture, uvs, colour = part.texture, part.uvs, part.colour
            emissive = 0.8 if obj.cls == "exit_sign" else 0.0
            if obj.cls == "poster" and obj.texture >= 0 and getattr(part, "role", "") == "picture":
                texture = textures.poster(obj.texture)
            elif scene.outside_views and is_pane(obj, part):
                texture, uvs = outside_part(obj, part, pos, scene, textures)
                colour, emissive = (1.0, 1.0, 1.0), DAYLIGHT
            out.append(RenderMesh(pos.astype(np.float32), nrm.astype(np.float32), uvs, texture, colour,
                                  instance_id=obj.instance_id, emissive=emissive))
    return out


def object_corners(obj: SceneObject) -> np.ndarray:
    """The 8 corners (8, 3) of an object's oriented bounding box in the map frame."""
    w, d, h = obj.size
    c, s = math.cos(obj.yaw + math.pi / 2), math.sin(obj.yaw + math.pi / 2)
    local = np.array([[x, y, z] for x in (-w / 2, w / 2) for y in (-d / 2, d / 2) for z in (0.0, h)])
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return local @ rot.T + np.array([obj.x, obj.y, obj.z])
