"""Object boxes from the renderer's instance-id buffer: occlusion-aware, with a minimum visible area.

A box is the tight pixel rectangle of an instance's visible pixels. An instance gets a box only if
enough of it is visible: at least `min_area_px` pixels and at least `min_visible_share` of the area its
projected bounding box would cover inside the image (so a chair hidden behind a desk but for a leg is
not labelled a chair). The projected area comes from the object's 3D box, an upper bound of its
silhouette, which makes the share conservative.

With lens distortion (`camera.effects.distortion`) the id buffer is the distorted image, resampled from a
larger pinhole render (`camera_effects.source_intrinsics`). The projected area is then the 3D box's pinhole
bounding rectangle on that render, measured in distorted-image pixels: each render pixel counts the area the
lens maps it to (|det| of the distortion's Jacobian), nothing where the distorted camera does not see (`Lens`,
an integral image, so one lookup per object). Visible pixels and projected area are both counted in the
distorted image, as without a lens, and a lens that is off gives the pinhole figure.
"""

from __future__ import annotations

import functools
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


@dataclass(frozen=True, eq=False)
class Lens:
    """A distorted camera `image` that sees a pinhole render `source` through the plumb_bob `coeffs`.

    `integral[j, i]` sums, over the render's pixels of rows < j and columns < i, the area (in distorted-image
    pixels) the lens maps each to: |det d(distorted)/d(ideal)| where the distorted camera sees it, 0 elsewhere."""

    image: Intrinsics
    source: Intrinsics
    coeffs: tuple[float, float, float, float, float]
    integral: np.ndarray

    @classmethod
    def of(cls, image: Intrinsics, coeffs, source: Intrinsics) -> Lens:
        return _lens(image, tuple(float(c) for c in coeffs), source)

    def area(self, u1: float, u2: float, v1: float, v2: float) -> float:
        """Distorted-image area of the render's pixels whose centres lie in [u1, u2] x [v1, v2]."""
        s = self.source
        i1, i2 = max(0, int(np.ceil(u1))), min(s.width, int(np.floor(u2)) + 1)
        j1, j2 = max(0, int(np.ceil(v1))), min(s.height, int(np.floor(v2)) + 1)
        if i1 >= i2 or j1 >= j2:
            return 0.0
        t = self.integral
        return float(t[j2, i2] - t[j1, i2] - t[j2, i1] + t[j1, i1])


@functools.lru_cache(maxsize=4)
def _lens(image: Intrinsics, coeffs: tuple, source: Intrinsics) -> Lens:
    k1, k2, p1, p2, k3 = coeffs
    v, u = np.mgrid[0:source.height, 0:source.width].astype(np.float64)
    x, y = (u - source.cx) / source.fx, (v - source.cy) / source.fy
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dradial = 2 * (k1 + r2 * (2 * k2 + 3 * r2 * k3))
    a = radial + x * x * dradial + 2 * p1 * y + 6 * p2 * x  # d xd / dx
    b = x * y * dradial + 2 * p1 * x + 2 * p2 * y  # d xd / dy = d yd / dx
    d = radial + y * y * dradial + 6 * p1 * y + 2 * p2 * x  # d yd / dy
    # Same focal lengths in both cameras: the pixel-area ratio is the normalised Jacobian's determinant.
    density = np.abs(a * d - b * b) * (image.fx * image.fy) / (source.fx * source.fy)
    ud, vd = xd * image.fx + image.cx, yd * image.fy + image.cy
    seen = (ud >= -0.5) & (ud < image.width - 0.5) & (vd >= -0.5) & (vd < image.height - 0.5)
    integral = np.zeros((source.height + 1, source.width + 1))
    integral[1:, 1:] = np.where(seen, density, 0.0).cumsum(0).cumsum(1)
    integral.setflags(write=False)
    return Lens(image, source, coeffs, integral)


def projected_area(obj: SceneObject, intrinsics: Intrinsics, map_from_cam, lens: Lens | None = None) -> float:
    """Area (px) inside the image of the projected 3D box; corners behind the camera are clamped to it. With a
    `lens`, `intrinsics` is the image's and the box is projected on the lens's pinhole source, see the module."""
    k = intrinsics if lens is None else lens.source
    u, v, depth = project_points(k, map_from_cam, object_corners(obj))
    if np.all(depth <= 0.05):
        return 0.0
    if np.any(depth <= 0.05):
        # Part of the box is behind the camera: it covers the image from the visible side outwards.
        return float(intrinsics.width * intrinsics.height)
    if lens is not None:
        return lens.area(u.min(), u.max(), v.min(), v.max())
    x1, x2 = np.clip([u.min(), u.max()], 0, intrinsics.width)
    y1, y2 = np.clip([v.min(), v.max()], 0, intrinsics.height)
    return float(max(0.0, x2 - x1) * max(0.0, y2 - y1))


def visible_boxes(ids: np.ndarray, objects: dict[int, SceneObject], intrinsics: Intrinsics, map_from_cam,
                  min_area_px: float, min_visible_share: float, lens: Lens | None = None) -> list[PixelBox]:
    """Boxes of the detector classes that are visible enough in this view (`ids`: the image's id buffer,
    distorted through `lens` when given)."""
    out = []
    for iid, (x1, y1, x2, y2, count) in sorted(instance_boxes(ids).items()):
        obj = objects.get(iid)
        if obj is None or not obj.cls or count < min_area_px:
            continue
        full = projected_area(obj, intrinsics, map_from_cam, lens)
        share = min(1.0, count / full) if full > 0 else 0.0
        if share < min_visible_share:
            continue
        out.append(PixelBox(iid, obj.cls, float(x1), float(y1), float(x2), float(y2), count, share))
    return out
