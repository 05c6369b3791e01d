"""A map.yaml whose origin has a yaw: the same grid turned in the map frame.

The filter works on the axis-aligned grid; poses are turned from the map frame into the grid's before the
replay and back after it (`turned`, `turned_cov`). nav2's AMCL ignores the yaw; map_server keeps it.
"""

from __future__ import annotations

import numpy as np


def grid_frame(occ):
    """(the map as an axis-aligned grid, map_from_grid (3,)): the filter works on the grid; a map.yaml whose
    origin has a yaw is the same grid turned in the map frame, so poses are turned in and out around it."""
    from dataclasses import replace

    pose = np.array([occ.origin_x, occ.origin_y, occ.origin_yaw])
    if not occ.origin_yaw:
        return occ, None
    return replace(occ, origin_x=0.0, origin_y=0.0, origin_yaw=0.0), pose


def turned(map_from_grid, poses: np.ndarray | None, inverse: bool = False) -> np.ndarray | None:
    """Poses (N, 3) from the grid frame to the map frame (`inverse`: map to grid); unchanged without a turn."""
    if map_from_grid is None or poses is None:
        return poses
    from pipeline.runtime.motion import compose2d, inverse2d

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(map_from_grid, dtype=np.float64).reshape(1, 3)
    return compose2d(np.repeat(inverse2d(a) if inverse else a, len(p), 0), p)


def turned_cov(map_from_grid, cov: np.ndarray) -> np.ndarray:
    if map_from_grid is None:
        return cov
    c, s = np.cos(map_from_grid[2]), np.sin(map_from_grid[2])
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r @ cov @ r.T


def with_gt(run, gt):
    from dataclasses import replace

    return replace(run, gt=gt)
