"""Headless rasteriser for the embedded reference site: RGB, exact instance ids and z-depth from one draw.

Runs OpenGL 3.3 core through moderngl on a standalone EGL context, which on a machine without a GPU is Mesa's llvmpipe
(multi-threaded rasterisation on the CPU). The scene is uploaded once (`set_scene`) and then rendered from many
poses; lighting is a per-call argument because it varies between runs of the same site.

Conventions (see `pipeline.sitegen.camera` for the full statement):
- map frame: metres, x/y on the floor, z up. Pose `map_from_cam = (x, y, z, yaw)`, yaw CCW from +x, optional pitch
  positive up, no roll.
- images: OpenCV pinhole, x right, y down, pixel centres at integer coordinates; row 0 is the top of the image.
- depth: z-depth along the optical axis in metres (not the ray length), `inf` where nothing was drawn.
- instance ids: exact uint32 from `RenderMesh.instance_id`, 0 for structure and for the background.
- uvs: OpenGL/OBJ convention, (0, 0) is the bottom-left of the texture image and v goes up; textures repeat.

Shading (in linear light, sRGB in and out):
    lit  = albedo * (ambient + sum_i intensity_i * |n . l_i| * falloff(d_i)) * exposure * tint
    out  = mix(lit, albedo, emissive)
with albedo = srgb_to_linear(texture) * colour, `falloff(d) = window(d) / (1 + (d / LIGHT_FALLOFF_M)^2)` and a smooth
window that reaches 0 at LIGHT_RANGE_M, so each fragment only loops over the lights of its floor cell. Lighting is
two-sided (|n . l|) and back faces are drawn because imported meshes have inconsistent winding.

Process note: loading triton's LLVM (through torchvision) after Mesa's crashes the process (torch 2.14.1),
so `_create_context` loads torchvision, when installed, before the first EGL context.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import SitelocError
from pipeline.sitegen.camera import (
    Intrinsics,
    Pose,
    cam_from_map_matrix,
    cam_from_map_rotation,
    frustum_planes_map,
    gl_projection,
)
from pipeline.sitegen.camera import project_points as project_points

__all__ = [
    "Intrinsics",
    "Lighting",
    "RenderError",
    "RenderMesh",
    "Renderer",
    "project_points",
]

LIGHT_FALLOFF_M = 2.0  # distance at which a point light's contribution has halved (before the window)
LIGHT_RANGE_M = 5.0  # a point light contributes nothing beyond this distance
LIGHT_CELLS_M = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)  # light-list cell sizes to try, finest first
MAX_LIGHTS = 4096  # 64 KiB of vec4 in a uniform block
CHUNK_M = 5.0  # geometry is cut into floor chunks of this size for CPU frustum culling
DRAW_BAND_M = 4.0  # chunks are drawn front to back in distance bands of this width
GAMMA = 2.2

INSTALL_HINT = (
    "install Mesa's EGL and OpenGL drivers (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri libegl-mesa0); "
    "without a GPU, Mesa's llvmpipe renders on the CPU"
)


class RenderError(SitelocError):
    """The renderer cannot run (no EGL / OpenGL 3.3) or was given geometry it cannot draw."""


@dataclass(frozen=True)
class RenderMesh:
    """Static geometry in the map/world frame: metres, x/y on the floor plane (the map frame of ROS map_server),
    z up. Texture uvs follow OBJ/OpenGL: (0, 0) is the bottom-left of the image, v up; they repeat."""

    positions: np.ndarray  # (N, 3) float32, non-indexed triangle soup, N % 3 == 0
    normals: np.ndarray  # (N, 3) float32
    uvs: np.ndarray  # (N, 2) float32 (ignored when texture is None)
    texture: np.ndarray | None  # (H, W, 3) uint8, or None for flat colour
    colour: tuple[float, float, float] = (0.8, 0.8, 0.8)  # diffuse RGB 0..1, multiplies the texture
    instance_id: int = 0  # 0 = structure/background; >0 = an object instance (written to the id buffer)
    emissive: float = 0.0  # 0..1, e.g. an exit sign's glowing face (unaffected by lighting)


@dataclass(frozen=True)
class Lighting:
    ambient: float = 0.35
    lights: tuple[tuple[float, float, float, float], ...] = ()  # point lights (x, y, z, intensity), world frame
    exposure: float = 1.0  # global gain (lighting that varies between runs)
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # colour temperature


# One interleaved vertex, 32 bytes: normals, emissive and colour as normalised bytes keep the vertex fetch small.
VERTEX_DTYPE = np.dtype(
    [("pos", "<f4", (3,)), ("nrm_emit", "u1", (4,)), ("uv", "<f4", (2,)), ("col", "u1", (4,)), ("iid", "<u4")]
)
VERTEX_FORMAT = "3f 4f1 2f 4f1 u"
ID_VERTEX_FORMAT = "3f 16x u"  # the id/depth-only program reads position and id, skips the rest

_VERTEX_SHADER = """
#version 330 core
uniform mat4 u_clip_from_map;
in vec3 in_pos;
in vec4 in_nrm_emit;
in vec2 in_uv;
in vec4 in_col;
in uint in_iid;
out vec3 v_nrm;
out vec2 v_uv;
flat out vec4 v_col_emit;
flat out uint v_iid;
void main() {
    gl_Position = u_clip_from_map * vec4(in_pos, 1.0);
    v_nrm = in_nrm_emit.xyz * (255.0 / 127.0) - (128.0 / 127.0);
    v_col_emit = vec4(in_col.rgb, in_nrm_emit.w);
    v_uv = in_uv;
    v_iid = in_iid;
}
"""

_FRAGMENT_SHADER = """
#version 330 core
// Lights and per-cell light lists live in uniform blocks: llvmpipe gathers from them far faster than from storage
// buffers or textures. CellBlock holds, as uint32 words, one header per floor cell (first slot << 8 | count),
// then the lights' indices as 16-bit slots, two per word, starting at slot 2 * n_cells.
layout(std140) uniform LightBlock { vec4 lights[MAX_LIGHTS]; };   // x, y, z, intensity
layout(std140) uniform CellBlock { uvec4 cell_words[CELL_VEC4S]; };
uniform sampler2D u_tex;
uniform vec2 u_grid_origin;
uniform float u_inv_cell;
uniform ivec2 u_grid_dims;
uniform float u_ambient;
uniform vec3 u_gain;            // exposure * tint
uniform float u_inv_falloff2;
uniform float u_inv_range2;
uniform vec3 u_cam_centre;      // map frame
uniform mat3 u_ray_from_window; // window (x, y, 1) -> map-frame ray with unit z-depth
in vec3 v_nrm;
in vec2 v_uv;
flat in vec4 v_col_emit;
flat in uint v_iid;
layout(location = 0) out vec4 f_rgb;
layout(location = 1) out uint f_iid;
layout(location = 2) out float f_z;

uint cell_word(uint i) { return cell_words[i >> 2u][i & 3u]; }

void main() {
    float z = 1.0 / gl_FragCoord.w;
    // The map point is rebuilt from the pixel and its depth rather than interpolated: fewer varyings make
    // llvmpipe's single-threaded triangle setup cheaper.
    vec3 pos = u_cam_centre + z * (u_ray_from_window * vec3(gl_FragCoord.xy, 1.0));
    vec3 albedo = pow(texture(u_tex, v_uv).rgb, vec3(GAMMA)) * v_col_emit.rgb;
    vec3 n = normalize(v_nrm);
    float irradiance = u_ambient;
    ivec2 c = ivec2(floor((pos.xy - u_grid_origin) * u_inv_cell));
    if (all(greaterThanEqual(c, ivec2(0))) && all(lessThan(c, u_grid_dims))) {
        uint header = cell_word(uint(c.y * u_grid_dims.x + c.x));
        uint slot = uint(2 * u_grid_dims.x * u_grid_dims.y) + (header >> 8u);
        uint end = slot + (header & 255u);
        for (; slot < end; ++slot) {
            vec4 light = lights[(cell_word(slot >> 1u) >> ((slot & 1u) * 16u)) & 65535u];
            vec3 to_light = light.xyz - pos;
            float d2 = max(dot(to_light, to_light), 1e-8);
            float r2 = d2 * u_inv_range2;
            float window = clamp(1.0 - r2 * r2, 0.0, 1.0);
            irradiance += light.w * abs(dot(n, to_light)) * inversesqrt(d2) * window * window
                / (1.0 + d2 * u_inv_falloff2);
        }
    }
    vec3 lit = albedo * irradiance * u_gain;
    vec3 linear = mix(lit, albedo, v_col_emit.a);
    f_rgb = vec4(pow(clamp(linear, 0.0, 1.0), vec3(1.0 / GAMMA)), 1.0);
    f_iid = v_iid;
    f_z = z;
}
"""

_ID_VERTEX_SHADER = """
#version 330 core
uniform mat4 u_clip_from_map;
in vec3 in_pos;
in uint in_iid;
flat out uint v_iid;
void main() {
    gl_Position = u_clip_from_map * vec4(in_pos, 1.0);
    v_iid = in_iid;
}
"""

_ID_FRAGMENT_SHADER = """
#version 330 core
flat in uint v_iid;
layout(location = 0) out uint f_iid;
layout(location = 1) out float f_z;
void main() {
    f_iid = v_iid;
    f_z = 1.0 / gl_FragCoord.w;
}
"""


@dataclass
class _Batch:
    """Meshes sharing one texture: one VBO, drawn chunk range by chunk range."""

    texture: Any  # moderngl.Texture
    vbo: Any  # moderngl.Buffer
    vao: Any  # moderngl.VertexArray of the shading program
    id_vao: Any | None  # moderngl.VertexArray of the id/depth program (MSAA only)


@dataclass(frozen=True)
class LightGrid:
    """Per floor cell, the lights that can reach it, packed into the fragment shader's two uniform blocks."""

    lights: np.ndarray  # (L, 4) float32: x, y, z, intensity
    words: np.ndarray  # uint32: n_cells headers (first slot << 8 | count), then 16-bit light indices, two per word
    origin: tuple[float, float]  # map-frame corner of cell (0, 0)
    cell: float  # cell size in metres
    dims: tuple[int, int]  # (nx, ny); (0, 0) when there are no lights


def build_light_grid(
    lights: Sequence[tuple[float, float, float, float]], cell: float, reach: float = LIGHT_RANGE_M
) -> LightGrid:
    """Bin point lights into floor cells by horizontal distance from the cell's rectangle (conservative in 3D).

    A fragment then loops over its cell's few lights instead of every light of the floor; the result is exact
    because the falloff window is zero beyond `reach`.
    """
    arr = np.asarray(lights, dtype=np.float32).reshape(-1, 4)
    if len(arr) == 0:
        return LightGrid(arr, np.zeros(0, np.uint32), (0.0, 0.0), cell, (0, 0))
    lo = arr[:, :2].min(axis=0).astype(np.float64) - reach
    hi = arr[:, :2].max(axis=0).astype(np.float64) + reach
    nx, ny = (int(v) for v in np.maximum(np.ceil((hi - lo) / cell), 1))
    x0 = lo[0] + cell * np.arange(nx)
    y0 = lo[1] + cell * np.arange(ny)
    # Horizontal distance from each light to each cell rectangle, separable in x and y.
    dx = np.maximum(np.maximum(x0[None, :] - arr[:, 0:1], arr[:, 0:1] - (x0[None, :] + cell)), 0.0)  # (L, nx)
    dy = np.maximum(np.maximum(y0[None, :] - arr[:, 1:2], arr[:, 1:2] - (y0[None, :] + cell)), 0.0)  # (L, ny)
    reaches = dy[:, :, None] ** 2 + dx[:, None, :] ** 2 <= reach**2  # (L, ny, nx)
    cell_idx, light_idx = np.nonzero(reaches.reshape(len(arr), -1).T)  # cells row-major (iy * nx + ix), sorted
    n_cells = nx * ny
    counts = np.bincount(cell_idx, minlength=n_cells)
    if counts.max() > 255:
        raise RenderError(f"{counts.max()} point lights reach one {cell} m floor cell; at most 255 are supported")
    firsts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slots = np.zeros(len(light_idx) + len(light_idx) % 2, np.uint32)
    slots[: len(light_idx)] = light_idx
    words = np.concatenate([(firsts << 8) | counts, slots[0::2] | (slots[1::2] << 16)]).astype(np.uint32)
    return LightGrid(arr, words, (float(lo[0]), float(lo[1])), cell, (nx, ny))


def fit_light_grid(lights: Sequence[tuple[float, float, float, float]], max_words: int) -> LightGrid:
    """The finest light grid whose packed lists fit the uniform block (large floors get coarser cells)."""
    if len(lights) > MAX_LIGHTS:
        raise RenderError(f"{len(lights)} point lights; the renderer supports at most {MAX_LIGHTS}")
    for cell in LIGHT_CELLS_M:
        try:
            grid = build_light_grid(lights, cell)
        except RenderError:
            continue
        if len(grid.words) <= max_words:
            return grid
    raise RenderError(
        f"{len(lights)} point lights over this floor do not fit the per-cell light lists "
        f"({max_words} words of uniform memory); use fewer lights"
    )


def _texture_key(texture: np.ndarray | None, by_id: dict[int, str]) -> str | None:
    """Batch key: None for flat colour, else a content hash (computed once per distinct array object)."""
    if texture is None:
        return None
    key = by_id.get(id(texture))
    if key is None:
        arr = np.ascontiguousarray(texture)
        digest = hashlib.blake2b(arr.tobytes(), digest_size=16).hexdigest()
        key = f"{arr.shape[0]}x{arr.shape[1]}:{digest}"
        by_id[id(texture)] = key
    return key


def _check_mesh(i: int, mesh: RenderMesh) -> None:
    pos = np.asarray(mesh.positions)
    n = len(pos)
    if pos.ndim != 2 or pos.shape[1] != 3 or n % 3 != 0:
        raise RenderError(f"mesh {i}: positions must be (N, 3) with N % 3 == 0 (a triangle soup), got {pos.shape}")
    if np.asarray(mesh.normals).shape != (n, 3):
        raise RenderError(f"mesh {i}: normals must be {(n, 3)} like positions, got {np.asarray(mesh.normals).shape}")
    if mesh.texture is not None:
        tex = mesh.texture
        if tex.dtype != np.uint8 or tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] == 0 or tex.shape[1] == 0:
            raise RenderError(f"mesh {i}: texture must be (H, W, 3) uint8, got {tex.shape} {tex.dtype}")
        if np.asarray(mesh.uvs).shape != (n, 2):
            raise RenderError(f"mesh {i}: uvs must be {(n, 2)} for a textured mesh, got {np.asarray(mesh.uvs).shape}")
    if not 0 <= int(mesh.instance_id) < 2**32:
        raise RenderError(f"mesh {i}: instance_id must fit in uint32, got {mesh.instance_id}")
    if not np.isfinite(pos).all():
        raise RenderError(f"mesh {i}: positions contain nan or inf")


def _pack_batch(meshes: Sequence[RenderMesh]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Interleave a batch's vertices, sorted by floor chunk, and return (vertices, chunk_first, chunk_min, chunk_max).

    chunk_first[k] is the first vertex of chunk k (plus a final sentinel = vertex count); chunk_min/max are the
    chunk's axis-aligned bounds in the map frame, for frustum culling.
    """
    counts = np.array([len(m.positions) for m in meshes])
    pos = np.concatenate([np.asarray(m.positions, dtype=np.float32) for m in meshes])
    nrm = np.concatenate([np.asarray(m.normals, dtype=np.float32) for m in meshes])
    uvs = np.concatenate(
        [
            np.asarray(m.uvs, np.float32) if m.texture is not None else np.zeros((len(m.positions), 2), np.float32)
            for m in meshes
        ]
    )
    colour = np.array([np.clip(m.colour, 0.0, 1.0) for m in meshes], dtype=np.float64)
    emissive = np.array([min(max(float(m.emissive), 0.0), 1.0) for m in meshes])
    iid = np.array([int(m.instance_id) for m in meshes], dtype=np.uint32)

    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(length > 1e-12, nrm / np.maximum(length, 1e-12), np.array([0.0, 0.0, 1.0], np.float32))
    verts = np.empty(len(pos), VERTEX_DTYPE)
    verts["pos"] = pos
    verts["nrm_emit"][:, :3] = np.clip(np.rint(nrm * 127.0 + 128.0), 0, 255)
    verts["nrm_emit"][:, 3] = np.repeat(np.rint(emissive * 255.0), counts)
    verts["uv"][:, 0] = uvs[:, 0]
    verts["uv"][:, 1] = 1.0 - uvs[:, 1]  # OBJ/GL v (up from the image bottom) -> texture rows stored top first
    verts["col"][:, :3] = np.repeat(np.rint(colour * 255.0), counts, axis=0)
    verts["col"][:, 3] = 255
    verts["iid"] = np.repeat(iid, counts)

    tris = pos.reshape(-1, 3, 3)
    centroid = tris.mean(axis=1)
    cell = np.floor(centroid[:, :2] / CHUNK_M).astype(np.int64)
    cell -= cell.min(axis=0)
    key = cell[:, 1] * (cell[:, 0].max() + 1) + cell[:, 0]
    order = np.argsort(key, kind="stable")
    key = key[order]
    verts = verts.reshape(-1, 3)[order].reshape(-1)
    tris = tris[order]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    chunk_min = np.minimum.reduceat(tris.min(axis=1), starts, axis=0)
    chunk_max = np.maximum.reduceat(tris.max(axis=1), starts, axis=0)
    chunk_first = np.concatenate([starts, [len(tris)]]) * 3
    return verts, chunk_first, chunk_min, chunk_max


def _index_vertices(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge identical vertices of a triangle soup into (unique vertices, uint32 index), in first-use order.

    llvmpipe shades vertices on one thread and caches them per index; a soup shades every corner of every triangle,
    so indexing shared corners (smooth surfaces, subdivided faces) cuts the single-threaded front end.
    """
    keys = np.ascontiguousarray(verts).view(np.dtype((np.void, verts.dtype.itemsize)))
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # unique vertices in the order they are first used
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return verts[first[order]], rank[inverse.ravel()].astype(np.uint32)


class Renderer:
    """An EGL context with reusable framebuffers; upload a scene once, render it from many poses.

    `samples > 0` antialiases the RGB image only: colour is rendered multisampled and resolved, and the id and depth
    buffers come from a second, single-sampled pass so that ids are never blended.
    """

    def __init__(self, intrinsics: Intrinsics, *, near: float = 0.05, far: float = 60.0, samples: int = 0):
        if not 0 < near < far:
            raise RenderError(f"need 0 < near < far, got near={near}, far={far}")
        self.intrinsics = intrinsics
        self.near = float(near)
        self.far = float(far)
        self.samples = int(samples)
        self.ctx = _create_context()
        self._scene_resources: list[Any] = []
        self._batches: list[_Batch] = []
        self._chunk_batch = np.zeros(0, np.int64)
        self._chunk_first = np.zeros(0, np.int64)
        self._chunk_count = np.zeros(0, np.int64)
        self._chunk_min = np.zeros((0, 3))
        self._chunk_max = np.zeros((0, 3))
        self.triangle_count = 0
        self.cull = True  # CPU frustum culling of floor chunks; off only to measure what it saves
        self._light_key: tuple | None = None
        self.light_grid: LightGrid | None = None
        try:
            with self.ctx:
                self._build_pipeline()
        except Exception:
            self.close()
            raise

    # ----------------------------------------------------------------------------------------------- set-up
    def _build_pipeline(self) -> None:
        import moderngl

        ctx = self.ctx
        size = (self.intrinsics.width, self.intrinsics.height)
        limit = ctx.info["GL_MAX_RENDERBUFFER_SIZE"]
        if max(size) > limit:
            raise RenderError(f"image size {size} exceeds the OpenGL renderbuffer limit {limit}")
        block_bytes = min(int(ctx.info["GL_MAX_UNIFORM_BLOCK_SIZE"]), 65536)
        if block_bytes < MAX_LIGHTS * 16:
            raise RenderError(f"OpenGL uniform blocks of {block_bytes} bytes are too small; need {MAX_LIGHTS * 16}")
        self._cell_words = block_bytes // 4
        fragment_shader = _FRAGMENT_SHADER.replace("GAMMA", repr(GAMMA)).replace("MAX_LIGHTS", str(MAX_LIGHTS))
        fragment_shader = fragment_shader.replace("CELL_VEC4S", str(self._cell_words // 4))
        self.program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=fragment_shader)
        self.program["u_tex"].value = 0
        self.program["LightBlock"].binding = 0
        self.program["CellBlock"].binding = 1
        self._light_ubo = ctx.buffer(reserve=MAX_LIGHTS * 16)
        self._cell_ubo = ctx.buffer(reserve=self._cell_words * 4)
        self._rgb_rb = ctx.renderbuffer(size, components=4)
        self._id_rb = ctx.renderbuffer(size, components=1, dtype="u4")
        self._z_rb = ctx.renderbuffer(size, components=1, dtype="f4")
        self._depth_rb = ctx.depth_renderbuffer(size)
        self.id_program = None
        if self.samples > 0:
            samples = min(self.samples, ctx.max_samples)
            self._ms_rgb_rb = ctx.renderbuffer(size, components=4, samples=samples)
            self._ms_depth_rb = ctx.depth_renderbuffer(size, samples=samples)
            self._ms_fbo = ctx.framebuffer([self._ms_rgb_rb], self._ms_depth_rb)
            self._resolve_fbo = ctx.framebuffer([self._rgb_rb])
            self._fbo = ctx.framebuffer([self._id_rb, self._z_rb], self._depth_rb)
            self.id_program = ctx.program(vertex_shader=_ID_VERTEX_SHADER, fragment_shader=_ID_FRAGMENT_SHADER)
            self._rgb_fbo = self._resolve_fbo
            self._id_attachment, self._z_attachment = 0, 1
        else:
            self._fbo = ctx.framebuffer([self._rgb_rb, self._id_rb, self._z_rb], self._depth_rb)
            self._rgb_fbo = self._fbo
            self._id_attachment, self._z_attachment = 1, 2
        self._white = ctx.texture((1, 1), 3, data=bytes([255, 255, 255]))
        self._moderngl = moderngl
        self._set_lights(())

    def set_scene(self, meshes: Sequence[RenderMesh]) -> None:
        """Upload static geometry, replacing any previous scene; meshes sharing a texture become one VBO."""
        with self._current():
            self._set_scene(meshes)

    def _set_scene(self, meshes: Sequence[RenderMesh]) -> None:
        by_id: dict[int, str] = {}
        groups: dict[str | None, list[RenderMesh]] = {}
        for i, mesh in enumerate(meshes):
            _check_mesh(i, mesh)
            if len(mesh.positions) == 0:
                continue
            groups.setdefault(_texture_key(mesh.texture, by_id), []).append(mesh)
        self._release_scene()
        ctx, mgl = self.ctx, self._moderngl
        chunk_batch, chunk_first, chunk_count, chunk_min, chunk_max = [], [], [], [], []
        triangles = 0
        for key, group in groups.items():
            verts, firsts, cmin, cmax = _pack_batch(group)
            triangles += len(verts) // 3
            if key is None:
                texture = self._white
            else:
                image = np.ascontiguousarray(group[0].texture)
                texture = ctx.texture((image.shape[1], image.shape[0]), 3, data=image, alignment=1)
                texture.build_mipmaps()
                texture.filter = (mgl.LINEAR_MIPMAP_LINEAR, mgl.LINEAR)
                texture.repeat_x = texture.repeat_y = True
                self._scene_resources.append(texture)
            unique, index = _index_vertices(verts)
            vbo = ctx.buffer(unique.tobytes())
            ibo = ctx.buffer(index.tobytes())
            vao = ctx.vertex_array(
                self.program,
                [(vbo, VERTEX_FORMAT, "in_pos", "in_nrm_emit", "in_uv", "in_col", "in_iid")],
                index_buffer=ibo,
                index_element_size=4,
            )
            id_vao = None
            if self.id_program is not None:
                id_vao = ctx.vertex_array(
                    self.id_program,
                    [(vbo, ID_VERTEX_FORMAT, "in_pos", "in_iid")],
                    index_buffer=ibo,
                    index_element_size=4,
                )
            self._scene_resources.extend(r for r in (vbo, ibo, vao, id_vao) if r is not None)
            b = len(self._batches)
            self._batches.append(_Batch(texture, vbo, vao, id_vao))
            chunk_batch.append(np.full(len(cmin), b))
            chunk_first.append(firsts[:-1])
            chunk_count.append(np.diff(firsts))
            chunk_min.append(cmin)
            chunk_max.append(cmax)
        if self._batches:
            self._chunk_batch = np.concatenate(chunk_batch)
            self._chunk_first = np.concatenate(chunk_first)
            self._chunk_count = np.concatenate(chunk_count)
            self._chunk_min = np.concatenate(chunk_min).astype(np.float64)
            self._chunk_max = np.concatenate(chunk_max).astype(np.float64)
        self.triangle_count = triangles

    def _release_scene(self) -> None:
        for resource in self._scene_resources:
            resource.release()
        self._scene_resources = []
        self._batches = []
        self._chunk_batch = np.zeros(0, np.int64)
        self.triangle_count = 0

    def _set_lights(self, lights: tuple[tuple[float, float, float, float], ...]) -> None:
        """Upload the per-cell light lists; cached, since a run keeps its lights and only the pose changes."""
        key = tuple(tuple(float(v) for v in light) for light in lights)
        if key == self._light_key:
            return
        grid = fit_light_grid(key, self._cell_words)
        lights_data = np.zeros((MAX_LIGHTS, 4), np.float32)
        lights_data[: len(grid.lights)] = grid.lights
        words = np.zeros(self._cell_words, np.uint32)
        words[: len(grid.words)] = grid.words
        self._light_ubo.write(lights_data.tobytes())
        self._cell_ubo.write(words.tobytes())
        prog = self.program
        prog["u_grid_origin"].value = grid.origin
        prog["u_inv_cell"].value = 1.0 / grid.cell
        prog["u_grid_dims"].value = grid.dims
        prog["u_inv_falloff2"].value = 1.0 / LIGHT_FALLOFF_M**2
        prog["u_inv_range2"].value = 1.0 / LIGHT_RANGE_M**2
        self._light_key = key
        self.light_grid = grid

    # ---------------------------------------------------------------------------------------------- render
    def _draw_ranges(self, map_from_cam: Pose, pitch: float) -> list[tuple[int, int, int]]:
        """(batch, first index, index count) to draw: the chunks inside the frustum, roughly front to back.

        Chunks are drawn by distance band (DRAW_BAND_M), and by batch within a band: near geometry first lets
        llvmpipe's early depth test skip the shading of what it hides, while grouping by batch keeps texture
        switches (about 10 us each on llvmpipe, five times a draw call) few. Contiguous ranges are merged.
        """
        n = len(self._chunk_batch)
        if n == 0:
            return []
        if self.cull:
            planes = frustum_planes_map(self.intrinsics, map_from_cam, self.near, self.far, pitch)
            normals = planes[:, None, :3]
            corner = np.where(normals > 0, self._chunk_max[None], self._chunk_min[None])  # the most inside corner
            idx = np.flatnonzero(np.all((normals * corner).sum(axis=2) + planes[:, None, 3] >= 0, axis=0))
            if len(idx) == 0:
                return []
        else:
            idx = np.arange(n)
        centre = np.asarray(map_from_cam[:3], np.float64)
        nearest = np.clip(centre, self._chunk_min[idx], self._chunk_max[idx])
        band = (np.linalg.norm(nearest - centre, axis=1) // DRAW_BAND_M).astype(np.int64)
        idx = idx[np.lexsort((idx, self._chunk_batch[idx], band))]
        batch = self._chunk_batch[idx]
        first = self._chunk_first[idx]
        count = self._chunk_count[idx]
        # A new run starts where the batch changes or the next chunk does not continue the previous range.
        new_run = np.ones(len(idx), bool)
        new_run[1:] = (batch[1:] != batch[:-1]) | (first[1:] != first[:-1] + count[:-1])
        starts = np.flatnonzero(new_run)
        run_count = np.add.reduceat(count, starts)
        return list(zip(batch[starts].tolist(), first[starts].tolist(), run_count.tolist(), strict=True))

    def render(
        self, map_from_cam: Pose, lighting: Lighting, pitch: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render from a camera pose; returns rgb (H, W, 3) uint8, instance (H, W) uint32, depth (H, W) float32.

        Depth is the z-depth along the optical axis in metres, inf where no geometry was drawn (there the id is 0
        and the colour black).
        """
        with self._current():
            return self._render(map_from_cam, lighting, pitch)

    def _render(
        self, map_from_cam: Pose, lighting: Lighting, pitch: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mgl = self._moderngl
        ctx = self.ctx
        clip_from_map = gl_projection(self.intrinsics, self.near, self.far) @ cam_from_map_matrix(map_from_cam, pitch)
        matrix_bytes = np.ascontiguousarray(clip_from_map.T, dtype=np.float32).tobytes()  # GL is column-major
        self._set_lights(lighting.lights)
        prog = self.program
        prog["u_clip_from_map"].write(matrix_bytes)
        prog["u_cam_centre"].value = tuple(float(v) for v in map_from_cam[:3])
        prog["u_ray_from_window"].write(self._ray_from_window(map_from_cam, pitch))
        prog["u_ambient"].value = float(lighting.ambient)
        prog["u_gain"].value = tuple(float(lighting.exposure) * float(t) for t in lighting.tint)
        self._light_ubo.bind_to_uniform_block(0)
        self._cell_ubo.bind_to_uniform_block(1)
        draws = self._draw_ranges(map_from_cam, pitch)

        ctx.enable_only(mgl.DEPTH_TEST)  # no blending, no face culling
        if self.samples > 0:
            self._ms_fbo.use()
            self._ms_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._draw(draws, id_pass=False)
            ctx.copy_framebuffer(self._resolve_fbo, self._ms_fbo)
            self.id_program["u_clip_from_map"].write(matrix_bytes)
            self._fbo.use()
            self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self._draw(draws, id_pass=True)
        else:
            self._fbo.use()
            self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)  # id 0, z 0 (-> inf below), black
            self._draw(draws, id_pass=False)
        return self._read()

    def _ray_from_window(self, map_from_cam: Pose, pitch: float) -> bytes:
        """Column-major mat3 taking window coordinates (u + 0.5, v + 0.5, 1) to the map-frame ray with z-depth 1."""
        k = self.intrinsics
        cam_from_window = np.array(
            [[1.0 / k.fx, 0.0, -(k.cx + 0.5) / k.fx], [0.0, 1.0 / k.fy, -(k.cy + 0.5) / k.fy], [0.0, 0.0, 1.0]]
        )
        map_from_window = cam_from_map_rotation(map_from_cam[3], pitch).T @ cam_from_window
        return np.ascontiguousarray(map_from_window.T, dtype=np.float32).tobytes()

    def _draw(self, draws: list[tuple[int, int, int]], *, id_pass: bool) -> None:
        mode = self._moderngl.TRIANGLES
        bound = None
        for b, first, count in draws:
            batch = self._batches[b]
            if id_pass:
                batch.id_vao.render(mode, vertices=count, first=first)
                continue
            if bound is not batch.texture:
                batch.texture.use(0)
                bound = batch.texture
            batch.vao.render(mode, vertices=count, first=first)

    def _read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Read the attachments straight into fresh numpy arrays (row 0 is already the image's top row)."""
        h, w = self.intrinsics.height, self.intrinsics.width
        rgb = np.empty((h, w, 3), np.uint8)
        instance = np.empty((h, w), np.uint32)
        depth = np.empty((h, w), np.float32)
        self._rgb_fbo.read_into(rgb, components=3, attachment=0, alignment=1)
        self._fbo.read_into(instance, components=1, attachment=self._id_attachment, dtype="u4", alignment=1)
        self._fbo.read_into(depth, components=1, attachment=self._z_attachment, dtype="f4", alignment=1)
        depth[depth <= 0.0] = np.inf  # cleared to 0; drawn fragments have z >= near > 0
        return rgb, instance, depth

    # --------------------------------------------------------------------------------------------- teardown
    def close(self) -> None:
        """Release the GL objects and the EGL context; safe to call twice."""
        ctx = getattr(self, "ctx", None)
        if ctx is None:
            return
        with ctx:
            self._release_scene()
        ctx.release()
        self.ctx = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def gl_info(self) -> dict[str, Any]:
        """GL_RENDERER, GL_VERSION and friends of the context (for benchmark and bug reports)."""
        with self._current():
            return dict(self.ctx.info)

    def _current(self) -> Any:
        """This renderer's context made current: several renderers may live in one thread, each with its own."""
        if self.ctx is None:
            raise RenderError("the renderer is closed")
        return self.ctx


def _load_torchvision_first() -> None:
    """torchvision pulls in triton, whose LLVM segfaults the process when Mesa's (llvmpipe) is already loaded;
    the other order is fine. Every context is made here, so loading torchvision first here covers every caller."""
    import importlib.util

    if importlib.util.find_spec("torchvision") is not None:
        import torchvision.ops  # noqa: F401


def _create_context() -> Any:
    """A standalone EGL context with OpenGL 3.3 core, or a RenderError saying what to install."""
    _load_torchvision_first()
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a declared dependency
        raise RenderError(f"moderngl is not installed ({exc}); pip install moderngl, and {INSTALL_HINT}") from exc
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as exc:
        raise RenderError(f"cannot create a headless OpenGL 3.3 context through EGL: {exc}; {INSTALL_HINT}") from exc
    return ctx


def egl_available() -> tuple[bool, str]:
    """Whether a context can be created here, and the reason when not (tests skip with it)."""
    try:
        ctx = _create_context()
    except RenderError as exc:
        return False, str(exc)
    ctx.release()
    return True, ""


def lambert_irradiance(point: np.ndarray, normal: np.ndarray, lighting: Lighting) -> float:
    """The shader's irradiance at one map point, in closed form (tests and scene tuning use it)."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    total = float(lighting.ambient)
    for x, y, z, intensity in lighting.lights:
        to_light = np.array([x, y, z]) - np.asarray(point, np.float64)
        d2 = max(float(to_light @ to_light), 1e-8)
        window = min(max(1.0 - (d2 / LIGHT_RANGE_M**2) ** 2, 0.0), 1.0) ** 2
        total += intensity * abs(float(n @ to_light)) / math.sqrt(d2) * window / (1.0 + d2 / LIGHT_FALLOFF_M**2)
    return total
