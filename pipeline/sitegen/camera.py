"""Pinhole camera conventions shared by the renderer and by anything that checks it in closed form.

Frames:
- map (world): metres, x/y on the floor plane (the map frame of ROS map_server), z up.
- cam: OpenCV optical frame, x right, y down, z forward (along the optical axis).

A camera pose is `map_from_cam = (x, y, z, yaw)` plus an optional `pitch`: the camera centre in the map frame,
the heading yaw (radians, counter-clockwise from +x, so yaw=pi/2 looks along +y) and pitch (radians, positive
looks up). There is no roll: the image's x axis stays horizontal.

Pixels (OpenCV convention): the centre of the pixel in column i, row j has image coordinates (u, v) = (i, j);
the pixel covers [i - 0.5, i + 0.5) x [j - 0.5, j + 0.5). So a centred principal point is
cx = (width - 1) / 2, and a projected point (u, v) lands on pixel (round(u), round(v)). COLMAP and OpenGL put
pixel centres at integer + 0.5: add 0.5 to cx and cy to convert. The renderer rasterises with exactly this
convention (a pixel is drawn when its centre (i, j) is inside the projected triangle).

Pure numpy: importing this module does not touch OpenGL.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Pose = tuple[float, float, float, float]  # (x, y, z, yaw) of the camera in the map frame


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, OpenCV convention (pixel centres at integer coordinates, see module doc)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov: float) -> Intrinsics:
        """Square pixels, centred principal point, horizontal field of view `hfov` in radians."""
        fx = (width / 2.0) / math.tan(hfov / 2.0)
        return cls(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def hfov(self) -> float:
        """Horizontal field of view (radians) for a centred principal point."""
        return 2.0 * math.atan((self.width / 2.0) / self.fx)

    def matrix(self) -> np.ndarray:
        """The 3x3 OpenCV camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def cam_from_map_rotation(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """Rotation R with p_cam = R @ (p_map - centre); rows are the cam x (right), y (down), z (forward) axes in map."""
    cy_, sy_ = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    forward = np.array([cp * cy_, cp * sy_, sp])
    right = np.array([sy_, -cy_, 0.0])  # horizontal, heading rotated by -90 deg
    down = np.cross(forward, right)  # z x x = y for a right-handed optical frame
    return np.stack([right, down, forward])


def cam_from_map_matrix(map_from_cam: Pose, pitch: float = 0.0) -> np.ndarray:
    """4x4 rigid transform taking homogeneous map points to the cam (optical) frame."""
    x, y, z, yaw = map_from_cam
    rot = cam_from_map_rotation(yaw, pitch)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ np.array([x, y, z], dtype=np.float64)
    return out


def project_points(
    intrinsics: Intrinsics, map_from_cam: Pose, points_world: np.ndarray, pitch: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project map-frame points (N, 3) to pixel coordinates with the renderer's conventions.

    Returns (u, v, depth), each (N,) float64: u right and v down in pixels (pixel centres at integers), depth the
    z-depth along the optical axis in metres. Points at or behind the camera centre (depth <= 0) get u = v = nan.
    """
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    cam_from_map = cam_from_map_matrix(map_from_cam, pitch)
    cam = pts @ cam_from_map[:3, :3].T + cam_from_map[:3, 3]
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(depth > 0, intrinsics.fx * cam[:, 0] / depth + intrinsics.cx, np.nan)
        v = np.where(depth > 0, intrinsics.fy * cam[:, 1] / depth + intrinsics.cy, np.nan)
    return u, v, depth


def gl_projection(intrinsics: Intrinsics, near: float, far: float) -> np.ndarray:
    """4x4 matrix from the cam (optical) frame to GL clip space, with image row v mapped to window row v.

    Window x = u + 0.5 and window y = v + 0.5 (GL samples pixel centres at integer + 0.5), so the pixel the GL
    rasteriser fills is exactly the OpenCV pixel of the projection, and `glReadPixels` row 0 is the image's top
    row (no flip on read-back; the mirrored winding is harmless because back-face culling is off).
    clip w = z_cam, so 1 / gl_FragCoord.w is the z-depth in metres.
    """
    w, h = intrinsics.width, intrinsics.height
    proj = np.zeros((4, 4))
    proj[0, 0] = 2.0 * intrinsics.fx / w
    proj[0, 2] = 2.0 * (intrinsics.cx + 0.5) / w - 1.0
    proj[1, 1] = 2.0 * intrinsics.fy / h
    proj[1, 2] = 2.0 * (intrinsics.cy + 0.5) / h - 1.0
    proj[2, 2] = (far + near) / (far - near)
    proj[2, 3] = -2.0 * far * near / (far - near)
    proj[3, 2] = 1.0
    return proj


def frustum_planes_map(
    intrinsics: Intrinsics, map_from_cam: Pose, near: float, far: float, pitch: float = 0.0
) -> np.ndarray:
    """The view frustum as 6 planes (a, b, c, d) in the map frame; a point p is inside when a*x + b*y + c*z + d >= 0.

    Used to skip whole chunks of geometry on the CPU before the (single-threaded on llvmpipe) vertex stage.
    """
    k = intrinsics
    # Planes in the cam frame as (nx, ny, nz, d) with n . p_cam + d >= 0 inside.
    cam_planes = np.array(
        [
            [k.fx, 0.0, k.cx + 0.5, 0.0],  # u >= -0.5
            [-k.fx, 0.0, k.width - 0.5 - k.cx, 0.0],  # u <= width - 0.5
            [0.0, k.fy, k.cy + 0.5, 0.0],  # v >= -0.5
            [0.0, -k.fy, k.height - 0.5 - k.cy, 0.0],  # v <= height - 0.5
            [0.0, 0.0, 1.0, -near],
            [0.0, 0.0, -1.0, far],
        ]
    )
    # n_cam . (T p_map) + d  ==  (T^T n_cam4) . p_map4
    return cam_planes @ cam_from_map_matrix(map_from_cam, pitch)
