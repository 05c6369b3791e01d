"""Rendering a site's images in several processes, each with its own single-threaded EGL context.

llvmpipe splits a frame into tiles over its threads, but the office floor's frames are small and most of a
frame's cost is serial (vertex processing, triangle setup, readback): on 2 cores, one context with 2 threads
renders 13.0 images/s against 11.6 with 1 thread, while two processes with 1 thread each render 16.6
(`benchmarks/render_benchmark.py --processes`). So `synth` renders through `RenderPool`: each worker dies with
the parent (`pipeline.workers.die_with_parent`: `kill -9` of `synth` leaves no renderer behind),
rebuilds the scene from the preset and seed (the same scene: generation is seeded), uploads it, and takes
batches of views: it renders each, applies the camera effects (`camera.effects`, `camera_effects`), writes the
image and, for capture views, returns the COCO boxes read from the (distorted) instance buffer. The parent
keeps every random draw (lighting, runs, laser) in its own order, so the site written is the same byte for byte
whatever the number of workers (a test compares them).

Camera effects keep that: a frame's noise comes from `frame_rng(seed, *view.frame)`, its motion blur from the
view, and its exposure gain either from the frame alone (capture views, and run frames when the auto-exposure
has no lag) or, when the gain lags behind earlier frames that other workers render, in two steps: `map` renders
and distorts the frame, leaves it in `STASH` and returns its exposure meter; the parent runs the run's
`AutoExposure` over the meters in frame order; `develop` then finishes each frame with its gain.

`workers=1` renders in the calling process, through the same `render_views` and `develop_frames`.

`engine="ray"` (`synth --engine ray`) renders on Ray actors instead of spawned processes: each actor opens the
same render context once, every batch is submitted at once, round robin, and the results come back in order.
A batch lost with its worker is run again on the restarted actor. Batches are Python objects (lighting, views,
boxes back), not rows of a table, and the caller overlaps them with laser casting, so this uses Ray's actors
directly rather than a Ray Dataset. On a cluster the site's output directory must be on storage every node
sees.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from pipeline.sitegen.camera_effects import Blur

if TYPE_CHECKING:
    from pipeline.sitegen.change import ChangeSpec  # a change with a wall move travels to the workers as it is

MAX_WORKERS = 4  # each worker holds the scene's textures and buffers (a few hundred MB for the office floor)
STASH = ".develop"  # distorted frames waiting for their lagged exposure gain, under the site's temporary directory


@dataclass(frozen=True)
class View:
    pose: tuple[float, float, float, float]  # map_from_cam x, y, z, yaw (radians)
    rel: str  # the image's path relative to the site directory
    boxes: bool  # capture views get COCO boxes; run frames do not
    frame: tuple[int, ...] = ()  # the ids of its noise generator, `frame_rng(seed, *frame)`
    blur: Blur = field(default_factory=Blur)  # the camera's motion while exposed (run frames)
    lagged: bool = False  # its exposure gain lags behind earlier frames: `map` stashes it for `develop`


class Rendered(NamedTuple):
    seconds: float  # rendering alone
    boxes: list | None  # capture views: the COCO boxes
    meter: float | None  # lagged views: the exposure meter, for the parent's `AutoExposure`
    effects_s: float = 0.0  # the camera effects and the encoding


@dataclass
class RenderContext:
    renderer: object
    objects: dict
    intrinsics: object  # the site's camera (the images written)
    min_box_area_px: float
    min_visible_share: float
    root: Path
    effects: object = None  # CameraEffects; None: every effect off
    source: object = None  # the pinhole canvas rendered (larger than `intrinsics` under distortion); None: the same
    lens: object = None  # boxes.Lens under distortion
    seed: int = 0

    def __post_init__(self) -> None:
        from pipeline.sitegen.camera_effects import CameraEffects

        self.effects = CameraEffects.off() if self.effects is None else self.effects
        self.source = self.intrinsics if self.source is None else self.source


def exposure_meter(ctx: RenderContext, rgb) -> float:
    """What the auto-exposure meters: the mean linear luminance of the distorted, vignetted frame, before gain."""
    import numpy as np

    from pipeline.sitegen.camera_effects import LUMA, mean_luminance, srgb_to_linear, vignetting_gain

    vig = ctx.effects.vignetting
    if not (vig.enabled and vig.strength > 0):
        return mean_luminance(rgb)
    return float(np.mean((srgb_to_linear(rgb) @ LUMA) * vignetting_gain(ctx.intrinsics, vig.strength)))


def _settled_gain(ctx: RenderContext, rgb) -> float:
    from pipeline.sitegen.camera_effects import AutoExposure

    ae = ctx.effects.auto_exposure
    return AutoExposure(ae).update(exposure_meter(ctx, rgb)) if ae.enabled else 1.0


def _write(ctx: RenderContext, view: View, rgb, gain: float) -> None:
    """Vignetting, `gain`, the view's blur, saturation, noise, quantisation and encoding; then the file."""
    from pipeline.sitegen.camera_effects import apply_photometric, encode, frame_rng

    out = apply_photometric(rgb, effects=ctx.effects, intrinsics=ctx.intrinsics, gain=gain, blur=view.blur,
                            rng=frame_rng(ctx.seed, *view.frame))
    path = ctx.root / view.rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode(out, ctx.effects)[0])


def stash_path(root: Path, view: View) -> Path:
    return Path(root) / STASH / (view.rel + ".npy")


def render_views(ctx: RenderContext, lighting, views: list[View]) -> list[Rendered]:
    """Render each view, distort it and its id buffer, box it from the distorted ids, and write it (or, when
    `lagged`, stash it and return its meter)."""
    import time

    import numpy as np

    from pipeline.sitegen.boxes import visible_boxes
    from pipeline.sitegen.camera_effects import apply_distortion

    out = []
    for v in views:
        t0 = time.perf_counter()
        rgb, ids, _ = ctx.renderer.render(v.pose, lighting)
        t1 = time.perf_counter()
        rgb, ids = apply_distortion(rgb, ids if v.boxes else None, ctx.intrinsics, ctx.effects, source=ctx.source)
        boxes = (visible_boxes(ids, ctx.objects, ctx.intrinsics, v.pose, ctx.min_box_area_px, ctx.min_visible_share,
                               ctx.lens) if v.boxes else None)
        meter = None
        if v.lagged:
            meter = exposure_meter(ctx, rgb)
            path = stash_path(ctx.root, v)
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, rgb)
        else:
            _write(ctx, v, rgb, _settled_gain(ctx, rgb))
        out.append(Rendered(t1 - t0, boxes, meter, time.perf_counter() - t1))
    return out


def develop_frames(ctx: RenderContext, views: list[View], gains: list[float]) -> list[float]:
    """Finish stashed frames with the gains the parent's auto-exposure gave them; seconds per frame."""
    import time

    import numpy as np

    out = []
    for v, gain in zip(views, gains, strict=True):
        t0 = time.perf_counter()
        path = stash_path(ctx.root, v)
        _write(ctx, v, np.load(path), gain)
        path.unlink()
        out.append(time.perf_counter() - t0)
    return out


def default_workers() -> int:
    from pipeline.machine import usable_core_count

    return max(1, min(usable_core_count(), MAX_WORKERS))


_WORKER: dict = {}


def _start_worker(preset_json: dict, seed: int, change: bool | ChangeSpec, allow_fallback: bool, root: str,
                  change_areas: tuple[str, ...] = ()) -> None:
    import os

    os.environ["LP_NUM_THREADS"] = "1"  # read when the EGL context is created, below
    from pipeline.sitegen.presets import SitePreset

    preset = SitePreset.model_validate(preset_json)
    _WORKER["ctx"], _ = open_render_context(preset, seed, change, allow_fallback, Path(root),  # lives with the process
                                            change_areas=change_areas)


def _start_pool_worker(parent_pid: int, *args) -> None:
    """The process pool's initializer: tie the worker's life to the parent's, then `_start_worker`."""
    from pipeline.workers import die_with_parent

    die_with_parent(parent_pid)
    _start_worker(*args)


class RenderActor:
    """A Ray actor holding one render context (the `_start_worker` of a Ray worker)."""

    def __init__(self, preset_json: dict, seed: int, change, allow_fallback: bool, root: str,
                 change_areas: tuple[str, ...] = ()):
        _start_worker(preset_json, seed, change, allow_fallback, root, change_areas)

    def render(self, batch):
        return _work(batch)

    def develop(self, batch):
        return _develop(batch)


def _work(batch):
    lighting, views = batch
    return render_views(_WORKER["ctx"], lighting, views)


def _develop(batch):
    views, gains = batch
    return develop_frames(_WORKER["ctx"], views, gains)


def open_render_context(preset, seed: int, change: bool | ChangeSpec, allow_fallback: bool, root: Path, scene=None,
                        library=None, change_areas: tuple[str, ...] = ()):
    """A renderer with the site's scene uploaded, and the context `render_views` needs; returns (ctx, renderer)
    (close the renderer when done)."""
    from pipeline.sitegen.assets import load_assets
    from pipeline.sitegen.decals import SiteTextures
    from pipeline.sitegen.geometry import object_meshes, structure_meshes
    from pipeline.sitegen.render import Renderer
    from pipeline.sitegen.site_scene import build_scene, intrinsics_of

    scene = scene if scene is not None else build_scene(preset, seed, change, change_areas)
    library = library if library is not None else load_assets(tuple(preset.furnishing.classes),
                                                              allow_fallback=allow_fallback)
    k = intrinsics_of(preset)
    effects = preset.camera.effects
    coeffs = effects.distortion.coeffs
    source, lens = k, None
    if any(coeffs):  # render a larger pinhole canvas that the lens resamples into the site's camera
        from pipeline.sitegen.boxes import Lens
        from pipeline.sitegen.camera_effects import source_intrinsics

        source = source_intrinsics(k, coeffs)
        lens = Lens.of(k, coeffs, source)
    renderer = Renderer(source)
    try:
        textures = SiteTextures(scene, library.textures["poster"], preset.identity.unique_pictures)
        renderer.set_scene(structure_meshes(scene, library) + object_meshes(scene, library, textures))
    except Exception:
        renderer.close()
        raise
    ctx = RenderContext(renderer, {o.instance_id: o for o in scene.objects}, k, preset.render.min_box_area_px,
                        preset.render.min_visible_share, root, effects=effects, source=source, lens=lens, seed=seed)
    return ctx, renderer


class RenderPool:
    """`map(batches)`: each (lighting, [View]) batch rendered, saved and boxed, results in order; `develop`:
    lagged frames finished with their gains.

    With `workers` > 1, spawned processes render (see the module's docstring); otherwise a renderer here does,
    with the caller's `scene` and `library` when given (built from the preset and seed when not). `engine`
    "ray": `workers` Ray actors render, on this machine or on the cluster at `ray_address`.
    """

    def __init__(self, preset, seed: int, change: bool | ChangeSpec, allow_fallback: bool, root: Path, *, workers: int,
                 scene=None, library=None, change_areas: tuple[str, ...] = (), engine: str = "local",
                 ray_address: str | None = None):
        self.workers, self.ctx, self._renderer, self._pool, self._actors = int(workers), None, None, None, None
        if engine == "ray":
            from pipeline.machine import usable_core_count
            from pipeline.ray_engine import connect

            if ray_address is None:  # a local Ray: the same clear error as the process pool's
                _require_egl()
            ray = connect(ray_address, num_cpus=None if ray_address else usable_core_count())
            remote = ray.remote(num_cpus=1, max_restarts=3, max_task_retries=3)(RenderActor)
            args = (preset.model_dump(mode="json"), seed, change, allow_fallback, str(root), tuple(change_areas))
            self._actors = [remote.remote(*args) for _ in range(self.workers)]
            self._ray = ray
        elif engine != "local":
            raise ValueError(f"engine must be local or ray, got '{engine}'")
        elif self.workers > 1:
            import multiprocessing
            import os
            from concurrent.futures import ProcessPoolExecutor

            _require_egl()
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_pool_worker,
                initargs=(os.getpid(), preset.model_dump(mode="json"), seed, change, allow_fallback, str(root),
                          tuple(change_areas)))
        else:
            self.ctx, self._renderer = open_render_context(preset, seed, change, allow_fallback, Path(root), scene,
                                                           library)

    def map(self, batches: Iterable[tuple[object, list[View]]]) -> Iterator[list[Rendered]]:
        """With workers, every batch is submitted now and rendered while the caller goes on; here, each is
        rendered as the iterator reaches it."""
        if self._actors is not None:
            return self._on_actors("render", batches)
        if self._pool is None:
            return (render_views(self.ctx, lighting, views) for lighting, views in batches)
        return _worker_errors(self._pool.map(_work, batches))

    def develop(self, batches: Iterable[tuple[list[View], list[float]]]) -> Iterator[list[float]]:
        """Each (views, gains) batch of stashed frames finished (`develop_frames`), submitted as `map` does."""
        if self._actors is not None:
            return self._on_actors("develop", batches)
        if self._pool is None:
            return (develop_frames(self.ctx, views, gains) for views, gains in batches)
        return _worker_errors(self._pool.map(_develop, batches))

    def _on_actors(self, method: str, batches: Iterable) -> Iterator:
        """Every batch submitted now, round robin over the actors; results in order."""
        refs = [getattr(self._actors[i % len(self._actors)], method).remote(b) for i, b in enumerate(batches)]
        return (self._ray.get(ref) for ref in refs)

    def close(self) -> None:
        if self._actors is not None:
            for actor in self._actors:
                self._ray.kill(actor)
            self._actors = None
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


def _require_egl() -> None:
    """Check EGL here, before workers start, so that a missing EGL is one clear error, not a broken pool."""
    from pipeline.sitegen.render import RenderError, egl_available

    ok, why = egl_available()
    if not ok:
        raise RenderError(why)


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
