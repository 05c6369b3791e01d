"""Rendering a site's images in several processes, each with its own single-threaded EGL context.

llvmpipe splits a frame into tiles over its threads, but the office floor's frames are small and most of a
frame's cost is serial (vertex processing, triangle setup, readback): on 2 cores, one context with 2 threads
renders 13.0 images/s against 11.6 with 1 thread, while two processes with 1 thread each render 16.6
(`benchmarks/render_benchmark.py --processes`). So `synth` renders through `RenderPool`: each worker
rebuilds the scene from the preset and seed (the same scene: generation is seeded), uploads it, and takes
batches of views: it renders each, writes the JPEG and, for capture views, returns the COCO boxes read from
the instance buffer. The parent keeps every random draw (lighting, runs, laser) in its own order, so the
site written is the same byte for byte whatever the number of workers (a test compares them).

`workers=1` renders in the calling process, through the same `render_views`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

MAX_WORKERS = 4  # each worker holds the scene's textures and buffers (a few hundred MB for the office floor)


@dataclass(frozen=True)
class View:
    pose: tuple[float, float, float, float]  # map_from_cam x, y, z, yaw (radians)
    rel: str  # the JPEG's path relative to the site directory
    boxes: bool  # capture views get COCO boxes; run frames do not


@dataclass
class RenderContext:
    renderer: object
    objects: dict
    intrinsics: object
    min_box_area_px: float
    min_visible_share: float
    root: Path


def render_views(ctx: RenderContext, lighting, views: list[View]) -> list[tuple[float, list | None]]:
    """Render, save and box each view: (render seconds, boxes or None) per view."""
    import time

    from pipeline.sitegen.boxes import visible_boxes
    from pipeline.sitegen.synth import save_jpeg

    out = []
    for v in views:
        t0 = time.perf_counter()
        rgb, ids, _ = ctx.renderer.render(v.pose, lighting)
        seconds = time.perf_counter() - t0
        save_jpeg(ctx.root / v.rel, rgb)
        boxes = (visible_boxes(ids, ctx.objects, ctx.intrinsics, v.pose, ctx.min_box_area_px, ctx.min_visible_share)
                 if v.boxes else None)
        out.append((seconds, boxes))
    return out


def default_workers() -> int:
    from pipeline.machine import usable_core_count

    return max(1, min(usable_core_count(), MAX_WORKERS))


_WORKER: dict = {}


def _start_worker(preset_json: dict, seed: int, change: bool, allow_fallback: bool, root: str) -> None:
    import os

    os.environ["LP_NUM_THREADS"] = "1"  # read when the EGL context is created, below
    from pipeline.sitegen.presets import SitePreset

    preset = SitePreset.model_validate(preset_json)
    _WORKER["ctx"], _ = open_render_context(preset, seed, change, allow_fallback, Path(root))  # lives with the process


def _work(batch):
    lighting, views = batch
    return render_views(_WORKER["ctx"], lighting, views)


def open_render_context(preset, seed: int, change: bool, allow_fallback: bool, root: Path, scene=None, library=None):
    """A renderer with the site's scene uploaded, and the context `render_views` needs; returns (ctx, renderer)
    (close the renderer when done)."""
    from pipeline.sitegen.assets import load_assets
    from pipeline.sitegen.decals import SiteTextures
    from pipeline.sitegen.geometry import object_meshes, structure_meshes
    from pipeline.sitegen.render import Renderer
    from pipeline.sitegen.synth import build_scene, intrinsics_of

    scene = scene if scene is not None else build_scene(preset, seed, change)
    library = library if library is not None else load_assets(tuple(preset.furnishing.classes),
                                                              allow_fallback=allow_fallback)
    k = intrinsics_of(preset)
    renderer = Renderer(k)
    try:
        textures = SiteTextures(scene, library.textures["poster"], preset.identity.unique_pictures)
        renderer.set_scene(structure_meshes(scene, library) + object_meshes(scene, library, textures))
    except Exception:
        renderer.close()
        raise
    ctx = RenderContext(renderer, {o.instance_id: o for o in scene.objects}, k, preset.render.min_box_area_px,
                        preset.render.min_visible_share, root)
    return ctx, renderer


class RenderPool:
    """`map(batches)`: each (lighting, [View]) batch rendered, saved and boxed, results in order.

    With `workers` > 1, spawned processes render (see the module's docstring); otherwise a renderer here does,
    with the caller's `scene` and `library` when given (built from the preset and seed when not).
    """

    def __init__(self, preset, seed: int, change: bool, allow_fallback: bool, root: Path, *, workers: int,
                 scene=None, library=None):
        self.workers, self.ctx, self._renderer, self._pool = int(workers), None, None, None
        if self.workers > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from pipeline.sitegen.render import RenderError, egl_available

            ok, why = egl_available()  # here, so that a missing EGL is one clear error, not a broken pool
            if not ok:
                raise RenderError(why)

            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                initargs=(preset.model_dump(mode="json"), seed, change, allow_fallback, str(root)))
        else:
            self.ctx, self._renderer = open_render_context(preset, seed, change, allow_fallback, Path(root), scene,
                                                           library)

    def map(self, batches: Iterable[tuple[object, list[View]]]) -> Iterator[list[tuple[float, list | None]]]:
        """With workers, every batch is submitted now and rendered while the caller goes on; here, each is
        rendered as the iterator reaches it."""
        if self._pool is None:
            return (render_views(self.ctx, lighting, views) for lighting, views in batches)
        return _worker_errors(self._pool.map(_work, batches))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> RenderPool:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _worker_errors(results: Iterator) -> Iterator:
    from concurrent.futures.process import BrokenProcessPool

    from pipeline.sitegen.render import RenderError

    try:
        yield from results
    except BrokenProcessPool as exc:
        raise RenderError(f"a rendering process died ({exc}; its own error, if any, is printed above); rerun with "
                          f"--workers 1 to render in this process") from None


def chunks(views: list[View], size: int) -> list[list[View]]:
    return [views[i:i + size] for i in range(0, len(views), size)]
