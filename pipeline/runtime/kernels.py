"""The filter's inner loops over particles x beams, compiled with numba, with numpy twins.

Why numba: a likelihood-field update of 5000 particles x 1081 beams is 5.4 M endpoint lookups. As
numpy array passes it takes about 110 ms on this machine (many temporaries of 5.4 M elements); as one
compiled loop it stays in registers (`benchmarks/filter_vs_nav2.py` prints both). The beam model
needs a ray cast per particle and beam, which numpy cannot express without per-step passes over every
live ray. numba is compiled on first use (cached on disk), so importing the runtime stays cheap.

Conventions: poses are laser poses in the map frame (x, y, theta), beams are (range, bearing) pairs in
the laser frame with only valid returns kept by the caller; grids are row 0 = lowest y, padded by one
cell (see `grid.LaserMap`).
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a declared dependency; the numpy twins keep the likelihood field usable without it
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba cannot be installed
    HAVE_NUMBA = False

    def njit(*_args, **_kwargs):
        return lambda f: f


# --------------------------------------------------------------------------------------- likelihood field


@njit(inline="always")
def _pose_frame(pose, inv_res, ox, oy):  # pragma: no cover - compiled
    """cos, sin and the padded-grid position of a laser pose, once per pose."""
    return math.cos(pose[2]), math.sin(pose[2]), (pose[0] - ox) * inv_res + 1.0, (pose[1] - oy) * inv_res + 1.0


@njit(inline="always")
def _endpoint_cell(frame, bx, by, inv_res, h2, w2):  # pragma: no cover - compiled
    """(row, col) in the padded grid of the endpoint of beam (bx, by) (laser frame), clipped to the grid."""
    c, s, gx0, gy0 = frame
    gx = gx0 + (c * bx - s * by) * inv_res
    gy = gy0 + (s * bx + c * by) * inv_res
    return min(max(int(math.floor(gy)), 0), h2 - 1), min(max(int(math.floor(gx)), 0), w2 - 1)


@njit(cache=True, fastmath=True, nogil=True)
def _field_sum_numba(poses, bx, by, field, inv_res, ox, oy, out):  # pragma: no cover - compiled
    h2, w2 = field.shape
    for i in range(poses.shape[0]):
        frame = _pose_frame(poses[i], inv_res, ox, oy)
        acc = 0.0
        for b in range(bx.shape[0]):
            iy, ix = _endpoint_cell(frame, bx[b], by[b], inv_res, h2, w2)
            acc += field[iy, ix]
        out[i] = acc


def endpoint_cells(poses: np.ndarray, bx: np.ndarray, by: np.ndarray, shape: tuple[int, int], resolution: float,
                   origin: tuple[float, float]) -> np.ndarray:
    """(N, B) flat indices into a padded grid of `shape` of each pose's beam endpoints (clipped to the grid)."""
    h2, w2 = shape
    inv = 1.0 / resolution
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    gx = (poses[:, 0:1] - origin[0]) * inv + 1.0 + (c * bx - s * by) * inv
    gy = (poses[:, 1:2] - origin[1]) * inv + 1.0 + (s * bx + c * by) * inv
    ix = np.clip(np.floor(gx), 0, w2 - 1).astype(np.int64)
    iy = np.clip(np.floor(gy), 0, h2 - 1).astype(np.int64)
    return iy * w2 + ix


def field_sum_numpy(poses: np.ndarray, bx: np.ndarray, by: np.ndarray, field: np.ndarray, resolution: float,
                    origin: tuple[float, float], chunk: int = 256) -> np.ndarray:
    """Sum over beams of `field` (padded grid) at each pose's beam endpoints: the numpy twin."""
    out = np.empty(len(poses), dtype=np.float64)
    flat = field.ravel()
    for k in range(0, len(poses), chunk):
        cells = endpoint_cells(poses[k:k + chunk], bx, by, field.shape, resolution, origin)
        out[k:k + chunk] = flat[cells].sum(axis=1, dtype=np.float64)
    return out


def field_sum(poses: np.ndarray, bx: np.ndarray, by: np.ndarray, field: np.ndarray, resolution: float,
              origin: tuple[float, float], backend: str = "auto") -> np.ndarray:
    """Per pose, the sum of `field` at the endpoints of beams (bx, by) = r (cos a, sin a) in the laser frame."""
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    if backend == "numpy" or (backend == "auto" and not HAVE_NUMBA):
        return field_sum_numpy(poses, bx, by, field, resolution, origin)
    out = np.empty(len(poses), dtype=np.float64)
    _field_sum_numba(poses, np.ascontiguousarray(bx, dtype=np.float64), np.ascontiguousarray(by, dtype=np.float64),
                     field, 1.0 / resolution, float(origin[0]), float(origin[1]), out)
    return out


@njit(cache=True, fastmath=True, nogil=True)
def _field_sums_numba(poses, bx, by, left_out, field, inv_res, ox, oy, fit, total):  # pragma: no cover - compiled
    h2, w2 = field.shape
    for i in range(poses.shape[0]):
        frame = _pose_frame(poses[i], inv_res, ox, oy)
        acc_in = 0.0
        acc_out = 0.0
        for b in range(bx.shape[0]):
            iy, ix = _endpoint_cell(frame, bx[b], by[b], inv_res, h2, w2)
            if left_out[b]:
                acc_out += field[iy, ix]
            else:
                acc_in += field[iy, ix]
        fit[i] = acc_in
        total[i] = acc_in + acc_out


def field_sums(poses: np.ndarray, bx: np.ndarray, by: np.ndarray, left_out: np.ndarray | None, field: np.ndarray,
               resolution: float, origin: tuple[float, float], backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """`field_sum` over the beams not `left_out` (bool per beam; None: none) and over all of them, in one pass."""
    if left_out is None or not left_out.any():
        total = field_sum(poses, bx, by, field, resolution, origin, backend)
        return total, total
    if backend == "numpy" or (backend == "auto" and not HAVE_NUMBA):
        fit = field_sum_numpy(np.ascontiguousarray(poses, dtype=np.float64), bx[~left_out], by[~left_out], field,
                              resolution, origin)
        return fit, fit + field_sum_numpy(np.ascontiguousarray(poses, dtype=np.float64), bx[left_out], by[left_out],
                                          field, resolution, origin)
    fit, total = np.empty(len(poses)), np.empty(len(poses))
    _field_sums_numba(np.ascontiguousarray(poses, dtype=np.float64), np.ascontiguousarray(bx, dtype=np.float64),
                      np.ascontiguousarray(by, dtype=np.float64), np.ascontiguousarray(left_out, dtype=np.bool_),
                      field, 1.0 / resolution, float(origin[0]), float(origin[1]), fit, total)
    return fit, total


@njit(cache=True, fastmath=True, nogil=True)
def _beam_agreement_numba(poses, bx, by, distance, near, inv_res, ox, oy, agree):  # pragma: no cover - compiled
    h2, w2 = distance.shape
    for i in range(poses.shape[0]):
        frame = _pose_frame(poses[i], inv_res, ox, oy)
        for b in range(bx.shape[0]):
            iy, ix = _endpoint_cell(frame, bx[b], by[b], inv_res, h2, w2)
            if distance[iy, ix] < near:
                agree[b] += 1.0


def beam_agreement(poses: np.ndarray, bx: np.ndarray, by: np.ndarray, distance: np.ndarray, near: float,
                   resolution: float, origin: tuple[float, float], backend: str = "auto") -> np.ndarray:
    """(B,) per beam, the share of poses whose endpoint lies less than `near` from an obstacle (`distance`:
    the padded distance grid): what beam skipping decides on."""
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    if len(poses) == 0:
        return np.zeros(len(bx))
    if backend == "numpy" or (backend == "auto" and not HAVE_NUMBA):
        agree = np.zeros(len(bx))
        for k in range(0, len(poses), 256):
            cells = endpoint_cells(poses[k:k + 256], bx, by, distance.shape, resolution, origin)
            agree += (distance.ravel()[cells] < near).sum(axis=0)
        return agree / len(poses)
    agree = np.zeros(len(bx), dtype=np.float64)
    _beam_agreement_numba(poses, np.ascontiguousarray(bx, dtype=np.float64),
                          np.ascontiguousarray(by, dtype=np.float64), distance, float(near), 1.0 / resolution,
                          float(origin[0]), float(origin[1]), agree)
    return agree / len(poses)


# --------------------------------------------------------------------------------------------- ray casting


@njit(cache=True, fastmath=False, nogil=True)
def _cast_numba(poses, angles, occupied, safe, inv_res, ox, oy, tmax_cells, out):  # pragma: no cover - compiled
    h, w = occupied.shape
    for i in range(poses.shape[0]):
        u0 = (poses[i, 0] - ox) * inv_res
        v0 = (poses[i, 1] - oy) * inv_res
        for b in range(angles.shape[0]):
            a = poses[i, 2] + angles[b]
            dx = math.cos(a)
            dy = math.sin(a)
            if dx == 0.0:
                dx = 1e-12
            if dy == 0.0:
                dy = 1e-12
            t = 0.0
            hit = tmax_cells
            while t < tmax_cells:
                u = u0 + t * dx
                v = v0 + t * dy
                col = int(math.floor(u))
                row = int(math.floor(v))
                if row < 0 or row >= h or col < 0 or col >= w:
                    break
                if occupied[row, col]:
                    hit = t
                    break
                step = safe[row, col]
                if step > 1.0:
                    t += step
                    continue
                # One exact DDA step: to the nearer of the next vertical and horizontal cell boundaries.
                nu = (col + 1.0 - u) / dx if dx > 0 else (col - u) / dx
                nv = (row + 1.0 - v) / dy if dy > 0 else (row - v) / dy
                t += min(nu, nv) + 1e-9
            out[i, b] = min(hit, tmax_cells) / inv_res


def safe_steps(occupied: np.ndarray) -> np.ndarray:
    """Per cell, how far (in cells) any ray starting inside it may jump without entering an occupied cell.

    Distance between cell centres minus the worst offset of a point in its cell plus the occupied square's
    half-diagonal: sqrt(2) cells together.
    """
    from scipy.ndimage import distance_transform_edt

    return (distance_transform_edt(~occupied) - math.sqrt(2.0)).astype(np.float64)


def cast_rays(poses: np.ndarray, angles: np.ndarray, occupied: np.ndarray, safe: np.ndarray, resolution: float,
              origin: tuple[float, float], range_max: float) -> np.ndarray:
    """(N, B) first-hit ranges (m) of beams `angles` from laser poses; range_max when nothing is hit."""
    if not HAVE_NUMBA:  # pragma: no cover
        raise RuntimeError("the beam model needs numba (pip install numba); the likelihood field does not")
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    out = np.empty((len(poses), len(angles)), dtype=np.float64)
    _cast_numba(poses, np.ascontiguousarray(angles, dtype=np.float64), occupied, safe, 1.0 / resolution,
                float(origin[0]), float(origin[1]), range_max / resolution, out)
    return out


# ------------------------------------------------------------------------------- precomputed range table


def build_range_table(occupied: np.ndarray, free: np.ndarray, resolution: float, origin: tuple[float, float],
                      n_angles: int, range_max: float, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray, float]:
    """Ranges from every free cell's centre in `n_angles` headings (bin centres), cast exactly.

    Returns (cell_index (H, W) int32: row of the table or -1 for a non-free cell, table (K, n_angles)
    uint16, unit m per count). Headings: bin j covers [-pi + j w, -pi + (j + 1) w), w = 2 pi / n_angles.
    """
    rows, cols = np.nonzero(free)
    cell_index = np.full(free.shape, -1, dtype=np.int32)
    cell_index[rows, cols] = np.arange(len(rows), dtype=np.int32)
    width = 2.0 * math.pi / n_angles
    angles = -math.pi + (np.arange(n_angles) + 0.5) * width
    unit = range_max / 65535.0
    safe = safe_steps(occupied)
    table = np.empty((len(rows), n_angles), dtype=np.uint16)
    for k in range(0, len(rows), chunk):
        r, c = rows[k:k + chunk], cols[k:k + chunk]
        poses = np.column_stack([origin[0] + (c + 0.5) * resolution, origin[1] + (r + 0.5) * resolution,
                                 np.zeros(len(r))])
        ranges = cast_rays(poses, angles, occupied, safe, resolution, origin, range_max)
        table[k:k + chunk] = np.round(ranges / unit).astype(np.uint16)
    return cell_index, table, unit


@njit(cache=True, fastmath=True, nogil=True)
def _beam_table_numba(poses, angles, z, cell_index, table, unit, inv_short, inv_res, ox, oy, range_max,
                      z_hit, z_short, z_max, z_rand, sigma, lam, out):  # pragma: no cover - compiled
    h, w = cell_index.shape
    n_angles = table.shape[1]
    bin_scale = n_angles / (2.0 * math.pi)
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    rand = z_rand / range_max
    two_pi = 2.0 * math.pi
    short_num = np.empty(z.shape[0])
    for b in range(z.shape[0]):  # z_short lambda exp(-lambda z_k) is the same for every particle
        short_num[b] = z_short * lam * math.exp(-lam * z[b])
    for i in range(poses.shape[0]):
        col = int(math.floor((poses[i, 0] - ox) * inv_res))
        row = int(math.floor((poses[i, 1] - oy) * inv_res))
        idx = -1
        if 0 <= row < h and 0 <= col < w:
            idx = cell_index[row, col]
        heading = poses[i, 2] + math.pi
        heading -= two_pi * math.floor(heading / two_pi)
        acc = 0.0
        prod = 1.0  # a running product, logged only when it nears the double's range: one log per ~100 beams
        for b in range(angles.shape[0]):
            u = 0
            if idx >= 0:
                a = heading + angles[b]
                if a < 0.0:  # heading in [0, 2 pi) and |angle| <= 2 pi: one correction suffices
                    a += two_pi
                elif a >= two_pi:
                    a -= two_pi
                j = int(a * bin_scale)
                if j >= n_angles:
                    j = n_angles - 1
                u = table[idx, j]
            zs = u * unit
            zb = z[b]
            if zb >= range_max:
                p = z_max
            else:
                d = (zb - zs) / sigma
                p = rand
                if d * d < 80.0:  # beyond ~9 sigma the Gaussian adds nothing a double can hold
                    p += z_hit * norm * math.exp(-0.5 * d * d)
                if zb < zs:
                    p += short_num[b] * inv_short[u]
            prod *= max(p, 1e-300)
            if prod < 1e-200 or prod > 1e200:
                acc += math.log(prod)
                prod = 1.0
        out[i] = acc + math.log(prod)


def short_normalisers(unit: float, lam: float) -> np.ndarray:
    """1 / (1 - exp(-lambda z*)) for every table count z* / unit (0 for z* = 0, which no reading is below)."""
    zs = np.arange(65536, dtype=np.float64) * unit
    with np.errstate(divide="ignore"):
        out = 1.0 / -np.expm1(-lam * zs)
    out[0] = 0.0
    return out


def beam_table_loglik(poses, angles, z, cell_index, table, unit, resolution, origin, range_max, cfg,
                      inv_short: np.ndarray | None = None) -> np.ndarray:
    """Per pose, the beam model's sum of log p(z_k | z*_k) with z* looked up in the range table."""
    if not HAVE_NUMBA:  # pragma: no cover
        raise RuntimeError("the beam model needs numba (pip install numba); the likelihood field does not")
    if inv_short is None:
        inv_short = short_normalisers(unit, cfg.lambda_short)
    out = np.empty(len(poses), dtype=np.float64)
    _beam_table_numba(np.ascontiguousarray(poses, dtype=np.float64), np.ascontiguousarray(angles, dtype=np.float64),
                      np.ascontiguousarray(z, dtype=np.float64), cell_index, table, float(unit), inv_short,
                      1.0 / resolution,
                      float(origin[0]), float(origin[1]), float(range_max), cfg.z_hit, cfg.z_short, cfg.z_max,
                      cfg.z_rand, cfg.sigma_hit, cfg.lambda_short, out)
    return out
