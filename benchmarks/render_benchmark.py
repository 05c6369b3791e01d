"""Time the headless site renderer on a synthetic office floor.

    .venv/bin/python benchmarks/render_benchmark.py [--objects 100] [--frames 60] [--lights 140] [--no-cull]

The scene: a 40 x 30 m textured floor and ceiling, 2.7 m outer walls, `--objects` boxes of ~2k triangles each
(every face subdivided into 13 x 13 quads) with 8 shared checker textures, and a grid of ceiling lights. Prints the
machine (platform, CPU, cores, GL_RENDERER), the scene's triangle count, then images/s at 224x224 and 640x480 for
random poses at camera height 1.2 m (60 deg horizontal field of view), after one warm-up frame per size.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import cpu_model  # noqa: E402
from pipeline.sitegen.render import Intrinsics, Lighting, Renderer, RenderMesh  # noqa: E402

FLOOR_X, FLOOR_Y, HEIGHT = 40.0, 30.0, 2.7


def checker(seed: int, size: int = 256, squares: int = 8) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a, b = rng.integers(40, 230, size=(2, 3))
    ij = (np.arange(size) * squares // size)[:, None] + (np.arange(size) * squares // size)[None, :]
    img = np.where((ij % 2 == 0)[..., None], a, b).astype(np.uint8)
    return img


def grid_face(origin: np.ndarray, du: np.ndarray, dv: np.ndarray, n: int, uv_scale: float = 1.0):
    """A parallelogram origin + s*du + t*dv split into n x n quads: (positions, normals, uvs) of a triangle soup."""
    s = np.linspace(0.0, 1.0, n + 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    i, j = i.ravel(), j.ravel()
    corners = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j), (i + 1, j + 1), (i, j + 1)]
    st = np.stack([np.stack([s[a], s[b]], axis=1) for a, b in corners], axis=1).reshape(-1, 2)
    pos = origin + st[:, :1] * du + st[:, 1:] * dv
    normal = np.cross(du, dv)
    normal = normal / np.linalg.norm(normal)
    uv = st * np.array([np.linalg.norm(du), np.linalg.norm(dv)]) * uv_scale
    return pos.astype(np.float32), np.tile(normal, (len(pos), 1)).astype(np.float32), uv.astype(np.float32)


def box(lo: np.ndarray, hi: np.ndarray, n: int):
    """Axis-aligned box with every face subdivided n x n (12 n^2 triangles)."""
    x0, y0, z0 = lo
    dx, dy, dz = hi - lo
    ex, ey, ez = np.array([dx, 0, 0]), np.array([0, dy, 0]), np.array([0, 0, dz])
    faces = [
        (lo, ey, ex),
        (lo + ez, ex, ey),
        (lo, ex, ez),
        (lo + ey, ez, ex),
        (lo, ez, ey),
        (lo + ex, ey, ez),
    ]
    parts = [grid_face(np.asarray(o, float), du, dv, n) for o, du, dv in faces]
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))


def build_scene(n_objects: int, seed: int = 0) -> list[RenderMesh]:
    rng = np.random.default_rng(seed)
    textures = [checker(k) for k in range(8)]
    meshes = []
    o = np.zeros(3)
    for origin, du, dv, tex in [
        (o, np.array([FLOOR_X, 0, 0]), np.array([0, FLOOR_Y, 0]), 0),  # floor
        (np.array([0, 0, HEIGHT]), np.array([0, FLOOR_Y, 0]), np.array([FLOOR_X, 0, 0]), 1),  # ceiling
        (o, np.array([FLOOR_X, 0, 0]), np.array([0, 0, HEIGHT]), 2),
        (np.array([0, FLOOR_Y, 0]), np.array([FLOOR_X, 0, 0]), np.array([0, 0, HEIGHT]), 2),
        (o, np.array([0, FLOOR_Y, 0]), np.array([0, 0, HEIGHT]), 3),
        (np.array([FLOOR_X, 0, 0]), np.array([0, FLOOR_Y, 0]), np.array([0, 0, HEIGHT]), 3),
    ]:
        pos, nrm, uv = grid_face(origin, du, dv, 4, uv_scale=0.5)
        meshes.append(RenderMesh(pos, nrm, uv, textures[tex]))
    for k in range(n_objects):
        size = rng.uniform([0.4, 0.4, 0.4], [1.6, 1.2, 1.8])
        lo = np.array([rng.uniform(0.5, FLOOR_X - 2), rng.uniform(0.5, FLOOR_Y - 2), 0.0])
        pos, nrm, uv = box(lo, lo + size, 13)
        meshes.append(
            RenderMesh(pos, nrm, uv, textures[4 + k % 4], colour=tuple(rng.uniform(0.6, 1.0, 3)), instance_id=k + 1)
        )
    return meshes


def ceiling_lights(n: int) -> tuple[tuple[float, float, float, float], ...]:
    nx = max(1, round(math.sqrt(n * FLOOR_X / FLOOR_Y)))
    ny = max(1, math.ceil(n / nx))
    xs = (np.arange(nx) + 0.5) * FLOOR_X / nx
    ys = (np.arange(ny) + 0.5) * FLOOR_Y / ny
    return tuple((float(x), float(y), HEIGHT - 0.05, 0.8) for x in xs for y in ys)[:n]


def time_size(meshes, width: int, height: int, frames: int, lighting: Lighting, cull: bool, samples: int) -> float:
    intrinsics = Intrinsics.from_hfov(width, height, math.radians(60))
    rng = np.random.default_rng(1)
    poses = [
        (
            float(rng.uniform(1, FLOOR_X - 1)),
            float(rng.uniform(1, FLOOR_Y - 1)),
            1.2,
            float(rng.uniform(-math.pi, math.pi)),
        )
        for _ in range(frames)
    ]
    with Renderer(intrinsics, samples=samples) as renderer:
        renderer.cull = cull
        t0 = time.perf_counter()
        renderer.set_scene(meshes)
        upload = time.perf_counter() - t0
        renderer.render(poses[0], lighting)  # warm-up: shader variants are compiled on first use
        t0 = time.perf_counter()
        for pose in poses:
            renderer.render(pose, lighting)
        elapsed = time.perf_counter() - t0
    rate = frames / elapsed
    print(
        f"  {width}x{height}: {rate:7.1f} images/s  ({1000 * elapsed / frames:6.1f} ms/image, {frames} frames, "
        f"set_scene {upload:.2f} s)"
    )
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, default=100)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--lights", type=int, default=140)
    parser.add_argument("--samples", type=int, default=0, help="MSAA samples for the RGB image (0 = off)")
    parser.add_argument("--no-cull", action="store_true", help="draw every chunk (measures what culling saves)")
    args = parser.parse_args()

    meshes = build_scene(args.objects)
    triangles = sum(len(m.positions) for m in meshes) // 3
    lighting = Lighting(lights=ceiling_lights(args.lights))
    print(f"platform: {platform.platform()}, python {platform.python_version()}, numpy {np.__version__}")
    print(f"cpu: {cpu_model()}, {os.cpu_count()} cores, LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'unset')}")
    with Renderer(Intrinsics.from_hfov(8, 8, 1.0)) as probe:
        info = probe.gl_info
    print(f"gl: {info['GL_RENDERER']}, {info['GL_VERSION']}")
    print(
        f"scene: {len(meshes)} meshes, {triangles} triangles, {len(lighting.lights)} lights, "
        f"culling {'off' if args.no_cull else 'on'}, samples {args.samples}"
    )
    for width, height, frames in [(224, 224, args.frames), (640, 480, max(10, args.frames // 3))]:
        time_size(meshes, width, height, frames, lighting, not args.no_cull, args.samples)


if __name__ == "__main__":
    main()
