"""A site's scene and camera from its preset and seed: what `synth` and every render worker build alike.

Apart from `synth` so that the render workers (`render_pool`) rebuild the scene without importing the stage
that drives them. The same preset and seed always give the same scene.
"""

from __future__ import annotations

import math

from pipeline.sitegen.presets import SitePreset


def intrinsics_of(preset: SitePreset):
    from pipeline.sitegen.camera import Intrinsics

    cam = preset.camera
    fx = (cam.width / 2) / math.tan(math.radians(cam.hfov_deg) / 2)
    return Intrinsics(cam.width, cam.height, fx, fx, cam.width / 2, cam.height / 2)


def build_scene(preset: SitePreset, seed: int, change, change_areas: tuple[str, ...] = ()):
    """The site's scene; with `change`, after the environment change (only in `change_areas` when given).
    `change` is a bool (True: the change of the default `ChangeSpec`) or a `ChangeSpec` (e.g. one that moves a
    wall too): the render workers rebuild the scene from what `RenderPool` hands them, so it says everything."""
    from pipeline.sitegen.change import ChangeSpec, change_scene
    from pipeline.sitegen.furnish import furnish_scene
    from pipeline.sitegen.layout import generate_plan

    scene = furnish_scene(generate_plan(preset, seed), preset, seed)
    if change:
        spec = change if isinstance(change, ChangeSpec) else ChangeSpec()
        scene = change_scene(scene, seed, spec, poster_pictures=preset.furnishing.poster_pictures,
                             unique_pictures=preset.identity.unique_pictures, areas=tuple(change_areas))
    return scene
