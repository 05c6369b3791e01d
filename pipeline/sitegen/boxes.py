"""Object boxes from the renderer's instance-id buffer: occlusion-aware, with a minimum visible area.

A box is the tight pixel rectangle of an instance's visible pixels. An instance gets a box only if
enough of it is visible: at least `min_area_px` pixels and at least `min_visible_share` of the area its
projected bounding box would cover inside the image (so a chair hidden behind a desk but for a leg is
not labelled a chair). The projected area comes from the object's 3D box, an upper bound of its
silhouette, which makes the share conservative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.sitegen.camera import Intrinsics, project_points
from pipeline.sitegen.geometry import object_corners
from pipeline.sitegen.scene import SceneObject


@dataclass(frozen=True)
class PixelBox:
    instance_id: int
    cls: str
    x1: float
    y1: float
    x2: float
    y2: float
    visible_px: int
    visible_share: float


def instance_boxes(ids: np.ndarray) -> dict[int, tuple[int, int, int, int, int]]:
    """For each non-zero id: (x_min, y_min, x_max + 1, y_max + 1, pixel count), vectorised."""
    flat = ids.ravel()
    mask = flat > 0
    if not mask.any():
        return {}
    h, w = ids.shape
    idx = np.nonzero(mask)[0]
    vals = flat[idx]
    order = np.argsort(vals, kind="stable")
    vals, idx = vals[order], idx[order]
    starts = np.r_[0, np.nonzero(np.diff(vals))[0] + 1]
    ys, xs = idx // w, idx % w
    out = {}
    for k, s in enumerate(starts):
        e = starts[k + 1] if k + 1 < len(starts) else len(vals)
        xx, yy = xs[s:e], ys[s:e]
        out[int(vals[s])] = (int(xx.min()), int(yy.min()), int(xx.max()) + 1, int(yy.max()) + 1, int(e - s))
    return out


def projected_area(obj: SceneObject, intrinsics: Intrinsics, map_from_cam) -> float:
    """Area (px) inside the image of the projected 3D box; corners behind the camera are clamped to it."""
    u, v, depth = project_points(intrinsics, map_from_cam, object_corners(obj))
    if np.all(depth <= 0.05):
        return 0.0
    if np.any(depth <= 0.05):
        # Part of the box is behind the camera: it covers the image from the visible side outwards.
        return float(intrinsics.width * intrinsics.height)
    x1, x2 = np.clip([u.min(), u.max()], 0, intrinsics.width)
    y1, y2 = np.clip([v.min(), v.max()], 0, intrinsics.height)
    return float(max(0.0, x2 - x1) * max(0.0, y2 - y1))


def visible_boxes(ids: np.ndarray, objects: dict[int, SceneObject], intrinsics: Intrinsics, map_from_cam,
                  min_area_px: float, min_visible_share: float) -> list[PixelBox]:
    """Boxes of the detector classes that are visible enough in this view."""
    out = []
    for iid, (x1, y1, x2, y2, count) in sorted(instance_boxes(ids).items()):
        obj = objects.get(iid)
        if obj is None or not obj.cls or count < min_area_px:
            continue
        full = projected_area(obj, intrinsics, map_from_cam)
        share = min(1.0, count / full) if full > 0 else 0.0
        if share < min_visible_share:
            continue
        out.append(PixelBox(iid, obj.cls, float(x1), float(y1), float(x2), float(y2), count, share))
    return out
