"""Camera realism for rendered frames: lens distortion, vignetting, auto-exposure, motion blur, noise, JPEG.

Order of effects, as light meets a real camera: the optics first (`apply_distortion` resamples the ideal
pinhole render into the distorted image, then vignetting darkens it by the field angle), then the exposure
(the auto-exposure gain and the motion blur, both in linear light), then the sensor (saturation at full
well, Poisson-Gaussian noise, quantisation to 8-bit sRGB), then the JPEG encoder. Every effect has its own
switch, every random draw comes from the caller's `numpy.random.Generator` (`frame_rng`), angles are
radians, and with every effect off the frame comes back unchanged, bit for bit.
"""

from __future__ import annotations

import functools
import io
import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from pipeline.config import Strict
from pipeline.errors import ConfigError
from pipeline.io.site import Distortion
from pipeline.sitegen.camera import Intrinsics

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance of linear RGB
TODAY_JPEG_QUALITY = 92  # what `siteloc synth` wrote before camera effects


class DistortionSpec(Strict):
    """Radial-tangential lens distortion (OpenCV's 5 coefficients, ROS's plumb_bob), on normalised coordinates."""

    enabled: bool = Field(True, description="distort the rendered pinhole image (site.yaml records the model)")
    k1: float = Field(-0.05, description="r^2 radial coefficient (negative: barrel)")
    k2: float = Field(0.01, description="r^4 radial coefficient")
    p1: float = Field(0.0, description="first tangential coefficient")
    p2: float = Field(0.0, description="second tangential coefficient")
    k3: float = Field(0.0, description="r^6 radial coefficient")

    @property
    def coeffs(self) -> tuple[float, float, float, float, float]:
        """(k1, k2, p1, p2, k3), all zero when disabled."""
        return (self.k1, self.k2, self.p1, self.p2, self.k3) if self.enabled else (0.0,) * 5


class VignettingSpec(Strict):
    """Gain 1 - strength * (1 - cos^4 theta), theta the pixel's field angle (pinhole; strength 1: the cos^4 law)."""

    enabled: bool = True
    strength: float = Field(0.5, ge=0, le=1, description="share of the natural cos^4 falloff (0: none)")


class AutoExposureSpec(Strict):
    """Gain that brings the frame's mean linear luminance to `target`, lagging by an exponential filter in log gain."""

    enabled: bool = True
    target: float = Field(0.18, gt=0, lt=1, description="mean linear luminance aimed at (18 % grey)")
    tau_frames: float = Field(3.0, ge=0, description="filter time constant in frames (0: no lag)")
    min_gain: float = Field(0.25, gt=0, description="smallest gain the camera reaches")
    max_gain: float = Field(8.0, gt=0, description="largest gain the camera reaches")

    @model_validator(mode="after")
    def _range(self) -> AutoExposureSpec:
        if self.min_gain > self.max_gain:
            raise ValueError(f"min_gain {self.min_gain} is above max_gain {self.max_gain}")
        return self


class MotionBlurSpec(Strict):
    """Blur from the camera's motion during the exposure; synth applies it to every run frame, mapping and query
    (the robot drives while the shutter is open), never to the capture stops' views (the caller says which)."""

    enabled: bool = True
    exposure_s: float = Field(0.01, ge=0, description="exposure time in seconds (0: no blur)")
    forward_depth_m: float | None = Field(3.0, gt=0, description="scene depth that turns forward speed into a "
                                          "radial blur (None: ignore forward motion, only the yaw rate blurs)")


class NoiseSpec(Strict):
    """Poisson-Gaussian sensor noise on linear light (full scale 1): variance = gain * signal + read_sigma^2."""

    enabled: bool = True
    gain: float = Field(0.001, ge=0, description="shot-noise variance per unit signal (1 / full-well electrons)")
    read_sigma: float = Field(0.002, ge=0, description="standard deviation of the read noise")


class CameraEffects(Strict):
    """Every camera effect, each with its own switch; the defaults are a plausible robot camera."""

    distortion: DistortionSpec = DistortionSpec()
    vignetting: VignettingSpec = VignettingSpec()
    auto_exposure: AutoExposureSpec = AutoExposureSpec()
    motion_blur: MotionBlurSpec = MotionBlurSpec()
    noise: NoiseSpec = NoiseSpec()
    jpeg_quality: int | None = Field(80, ge=1, le=100, description="JPEG quality of the written frames (80: ROS "
                                     "compressed_image_transport's default; None: lossless PNG)")

    @classmethod
    def off(cls, jpeg_quality: int | None = TODAY_JPEG_QUALITY) -> CameraEffects:
        """Every effect off: the ideal pinhole frames synth wrote before, JPEG at quality 92 unless told."""
        return cls(distortion=DistortionSpec(enabled=False), vignetting=VignettingSpec(enabled=False),
                   auto_exposure=AutoExposureSpec(enabled=False), motion_blur=MotionBlurSpec(enabled=False),
                   noise=NoiseSpec(enabled=False), jpeg_quality=jpeg_quality)


def frame_rng(seed: int, *ids: int) -> np.random.Generator:
    """The generator of one frame, from the site seed and the frame's ids: the same whoever renders it, in any order."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *(int(i) for i in ids)]))


def site_distortion(spec: DistortionSpec) -> Distortion | None:
    """site.yaml's `camera.distortion` for the spec (None when off or all zero)."""
    coeffs = spec.coeffs
    return Distortion(coeffs=coeffs) if any(coeffs) else None


# --- colour -----------------------------------------------------------------------------------------------------

_DECODE = np.where(np.arange(256) / 255.0 <= 0.04045, np.arange(256) / 255.0 / 12.92,
                   ((np.arange(256) / 255.0 + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_to_linear(rgb_u8: np.ndarray) -> np.ndarray:
    """8-bit sRGB -> linear light in [0, 1], float32 (the IEC 61966-2-1 curve)."""
    return _DECODE[np.asarray(rgb_u8, dtype=np.uint8)]


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear light -> 8-bit sRGB, clipped to [0, 1] and rounded."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4, dtype=np.float32) - 0.055)
    return np.rint(s * 255.0).astype(np.uint8)


def mean_luminance(rgb_u8: np.ndarray) -> float:
    """The auto-exposure meter: the mean Rec. 709 luminance of the frame in linear light."""
    return float(np.mean(srgb_to_linear(rgb_u8)[..., :3] @ LUMA))


# --- distortion --------------------------------------------------------------------------------------------------

def _forward(x: np.ndarray, y: np.ndarray, c) -> tuple[np.ndarray, np.ndarray]:
    k1, k2, p1, p2, k3 = c
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def distort_points(points: np.ndarray, intrinsics: Intrinsics, coeffs) -> np.ndarray:
    """Ideal pinhole pixels (N, 2) as (u, v) -> where the distorted camera images them (plumb_bob model)."""
    k, p = intrinsics, np.asarray(points, dtype=np.float64).reshape(-1, 2)
    xd, yd = _forward((p[:, 0] - k.cx) / k.fx, (p[:, 1] - k.cy) / k.fy, coeffs)
    return np.column_stack([xd * k.fx + k.cx, yd * k.fy + k.cy])


def undistort_points(points: np.ndarray, intrinsics: Intrinsics, coeffs, *, tol: float = 1e-12,
                     max_iter: int = 50) -> np.ndarray:
    """Distorted pixels (N, 2) -> ideal pinhole pixels: the forward model inverted by Newton's method."""
    k, p = intrinsics, np.asarray(points, dtype=np.float64).reshape(-1, 2)
    xd, yd = (p[:, 0] - k.cx) / k.fx, (p[:, 1] - k.cy) / k.fy
    x, y = xd.copy(), yd.copy()
    k1, k2, p1, p2, k3 = coeffs
    for _ in range(max_iter):
        fx_, fy_ = _forward(x, y, coeffs)
        ex, ey = fx_ - xd, fy_ - yd
        if max(np.max(np.abs(ex), initial=0.0), np.max(np.abs(ey), initial=0.0)) < tol:
            break
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = 2 * (k1 + r2 * (2 * k2 + 3 * r2 * k3))  # d radial / d r2, times 2 (d r2 / dx = 2x)
        a = radial + x * x * dradial + 2 * p1 * y + 6 * p2 * x  # d xd / dx
        b = x * y * dradial + 2 * p1 * x + 2 * p2 * y  # d xd / dy = d yd / dx
        d = radial + y * y * dradial + 6 * p1 * y + 2 * p2 * x  # d yd / dy
        det = a * d - b * b
        x, y = x - (d * ex - b * ey) / det, y - (a * ey - b * ex) / det
    else:
        raise ConfigError(f"lens distortion {tuple(coeffs)} cannot be inverted over this {k.width}x{k.height} "
                          "image (the model folds over): use smaller coefficients")
    return np.column_stack([x * k.fx + k.cx, y * k.fy + k.cy])


def source_intrinsics(intrinsics: Intrinsics, coeffs) -> Intrinsics:
    """The pinhole canvas (same focal lengths, grown by whole pixels) that sees every ray of the distorted image:
    render this and `distort_image(..., source=it)` leaves no unseen border (barrel distortion needs it)."""
    k = intrinsics
    u = np.arange(-0.5, k.width, 1.0).clip(max=k.width - 0.5)
    v = np.arange(-0.5, k.height, 1.0).clip(max=k.height - 0.5)
    edge = np.concatenate([np.column_stack([u, np.full_like(u, e)]) for e in (-0.5, k.height - 0.5)]
                          + [np.column_stack([np.full_like(v, e), v]) for e in (-0.5, k.width - 0.5)])
    ideal = undistort_points(edge, k, coeffs)
    pad = [max(0, math.ceil(-ideal[:, i].min()) + 1) for i in (0, 1)]
    far = [max(0, math.ceil(ideal[:, i].max() - n + 1) + 1) for i, n in ((0, k.width), (1, k.height))]
    return Intrinsics(k.width + pad[0] + far[0], k.height + pad[1] + far[1], k.fx, k.fy, k.cx + pad[0],
                      k.cy + pad[1])


@functools.lru_cache(maxsize=4)
def _sample_grid(intrinsics: Intrinsics, coeffs: tuple, source: Intrinsics) -> np.ndarray:
    v, u = np.mgrid[0:intrinsics.height, 0:intrinsics.width]
    ideal = undistort_points(np.column_stack([u.ravel(), v.ravel()]), intrinsics, coeffs)
    us = (ideal[:, 0] - intrinsics.cx) / intrinsics.fx * source.fx + source.cx
    vs = (ideal[:, 1] - intrinsics.cy) / intrinsics.fy * source.fy + source.cy
    return np.stack([vs, us]).reshape(2, intrinsics.height, intrinsics.width)


@functools.lru_cache(maxsize=4)
def _bilinear_taps(intrinsics: Intrinsics, coeffs: tuple, source: Intrinsics):
    """Per output pixel: the flat indices of its 4 source neighbours, the weights along u and v, and whether its
    ray falls inside the render (the sample grid turned into a gather, 3x faster than map_coordinates)."""
    vs, us = (a.ravel() for a in _sample_grid(intrinsics, coeffs, source))
    inside = (us >= 0) & (us <= source.width - 1) & (vs >= 0) & (vs <= source.height - 1)
    u, v = np.where(inside, us, 0.0), np.where(inside, vs, 0.0)
    u0, v0 = np.floor(u).astype(np.intp), np.floor(v).astype(np.intp)
    u1, v1 = np.minimum(u0 + 1, source.width - 1), np.minimum(v0 + 1, source.height - 1)
    w = source.width
    index = tuple(a.astype(np.intp) for a in (v0 * w + u0, v0 * w + u1, v1 * w + u0, v1 * w + u1))
    return index, (u - u0).astype(np.float32), (v - v0).astype(np.float32), inside


def distort_image(img: np.ndarray, intrinsics: Intrinsics, coeffs, *, nearest: bool = False,
                  source: Intrinsics | None = None, fill: float = 0) -> np.ndarray:
    """The distorted camera's image (intrinsics + coeffs) of an ideal pinhole render `img` taken with `source`
    (default: `intrinsics`). Bilinear, or nearest (`nearest`: ids stay values of the input); rays outside the
    render get `fill`. Same dtype as the input; (H, W) or (H, W, C)."""
    from scipy.ndimage import map_coordinates

    source = intrinsics if source is None else source
    img = np.asarray(img)
    if img.shape[:2] != (source.height, source.width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, the source camera {source.width}x{source.height}")
    coeffs = tuple(float(c) for c in coeffs)
    planes = img[..., None] if img.ndim == 2 else img
    if nearest:
        grid = _sample_grid(intrinsics, coeffs, source)
        out = np.stack([map_coordinates(planes[..., c], grid, order=0, mode="constant", cval=fill)
                        for c in range(planes.shape[2])], axis=-1)
    else:
        (i00, i01, i10, i11), fu, fv, inside = _bilinear_taps(intrinsics, coeffs, source)
        out = np.empty((intrinsics.height * intrinsics.width, planes.shape[2]), np.float32)
        for c in range(planes.shape[2]):
            plane = np.ascontiguousarray(planes[..., c]).ravel()
            a, b = plane[i00].astype(np.float32), plane[i01].astype(np.float32)
            top = a + (b - a) * fu
            a, b = plane[i10].astype(np.float32), plane[i11].astype(np.float32)
            bottom = a + (b - a) * fu
            out[:, c] = top + (bottom - top) * fv
        out[~inside] = fill
        out = out.reshape(intrinsics.height, intrinsics.width, planes.shape[2])
    if not nearest and np.issubdtype(img.dtype, np.integer):
        info = np.iinfo(img.dtype)
        out = np.clip(np.rint(out), info.min, info.max)
    out = out.astype(img.dtype)
    return out[..., 0] if img.ndim == 2 else out


def apply_distortion(rgb: np.ndarray, ids: np.ndarray | None, intrinsics: Intrinsics, effects: CameraEffects, *,
                     source: Intrinsics | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The optics' geometry: rgb bilinear and the instance-id buffer nearest (recompute boxes from it)."""
    coeffs = effects.distortion.coeffs
    if not any(coeffs) and (source is None or source == intrinsics):
        return rgb, ids
    out = distort_image(rgb, intrinsics, coeffs, source=source)
    return out, None if ids is None else distort_image(ids, intrinsics, coeffs, nearest=True, source=source)


# --- photometry ---------------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def vignetting_gain(intrinsics: Intrinsics, strength: float) -> np.ndarray:
    """(H, W) gain 1 - strength * (1 - cos^4 theta), theta = atan(|((u - cx) / fx, (v - cy) / fy)|); read-only."""
    k = intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width]
    tan2 = ((u - k.cx) / k.fx) ** 2 + ((v - k.cy) / k.fy) ** 2
    gain = (1.0 - strength * (1.0 - 1.0 / (1.0 + tan2) ** 2)).astype(np.float32)  # cos^2 = 1 / (1 + tan^2)
    gain.setflags(write=False)
    return gain


@dataclass(frozen=True)
class Blur:
    """Image motion during the exposure: a uniform shift (dx, dy) in pixels plus a radial `zoom` (relative
    growth of the image about the principal point). The frame shows the scene at mid-exposure."""

    shift: tuple[float, float] = (0.0, 0.0)
    zoom: float = 0.0


def blur_from_motion(intrinsics: Intrinsics, spec: MotionBlurSpec, *, yaw_rate: float, speed: float) -> Blur:
    """The blur of a camera turning at `yaw_rate` (rad/s, CCW) and moving forward at `speed` (m/s) while exposed.
    A turn to the left moves the scene right by fx * yaw_rate * exposure; forward motion grows the image by
    speed * exposure / forward_depth_m. Pass the rates of the motion itself (zero across a kidnapping)."""
    if not spec.enabled or spec.exposure_s == 0:
        return Blur()
    zoom = 0.0 if spec.forward_depth_m is None else speed * spec.exposure_s / spec.forward_depth_m
    return Blur((intrinsics.fx * yaw_rate * spec.exposure_s, 0.0), zoom)


def motion_blur(linear: np.ndarray, blur: Blur, centre: tuple[float, float] | None = None) -> np.ndarray:
    """(H, W, C) float image averaged along the motion: out(p) = mean over t in [-1/2, 1/2] of
    img(p - t * (shift + zoom * (p - centre))). A point becomes a streak of |shift| + 1 pixels (integer shift),
    total energy kept; borders repeat the edge. A line kernel when zoom is 0, else resampled taps."""
    from scipy.ndimage import convolve

    img = np.asarray(linear, dtype=np.float32)
    h, w = img.shape[:2]
    cx, cy = ((w - 1) / 2, (h - 1) / 2) if centre is None else centre
    sx, sy = blur.shift
    reach = math.hypot(sx, sy) + abs(blur.zoom) * math.hypot(max(cx, w - 1 - cx), max(cy, h - 1 - cy))
    n = math.ceil(reach - 1e-9) + 1
    if n < 2:
        return img
    ts = np.linspace(-0.5, 0.5, n)
    if blur.zoom == 0:
        rx, ry = math.ceil(abs(sx) / 2), math.ceil(abs(sy) / 2)
        kernel = np.zeros((2 * ry + 1, 2 * rx + 1, 1), np.float32)
        for t in ts:  # a tap reading img(p - t * shift), splatted bilinearly (convolve reads in[p + c - j])
            x, y = rx + t * sx, ry + t * sy
            x0, y0 = min(math.floor(x), 2 * rx - 1) if rx else 0, min(math.floor(y), 2 * ry - 1) if ry else 0
            fx_, fy_ = x - x0, y - y0
            for dy, wy in ((0, 1 - fy_), (1, fy_)):
                for dx, wx in ((0, 1 - fx_), (1, fx_)):
                    if wx * wy > 0:
                        kernel[y0 + dy, x0 + dx, 0] += wx * wy / n
        return convolve(img, kernel, mode="nearest")
    planes = np.ascontiguousarray(np.moveaxis(img[..., None] if img.ndim == 2 else img, -1, 0))  # (C, H, W)
    out = np.zeros_like(planes)
    for t in ts:
        if abs(t) < 1e-12:  # the middle tap of an odd count is the frame itself
            out += planes
            continue
        # The tap reads img at (1 - t zoom) p + t (zoom c - shift): a scale and shift per axis, so bilinear
        # sampling separates into columns then rows (edges repeated, as scipy's mode "nearest"); plane by plane
        # and in place, 3x faster than affine_transform.
        s = 1.0 - t * blur.zoom
        r0, r1, wr = _axis_taps(h, s, t * blur.zoom * cy - t * sy)
        c0, c1, wc = _axis_taps(w, s, t * blur.zoom * cx - t * sx)
        for plane, acc in zip(planes, out, strict=True):
            cols, step = np.take(plane, c0, axis=1), np.take(plane, c1, axis=1)
            step -= cols
            step *= wc
            cols += step
            acc += np.take(cols, r0, axis=0)
            step = np.take(cols, r1, axis=0)
            step -= np.take(cols, r0, axis=0)
            step *= wr[:, None]
            acc += step
    out /= n
    return out[0] if img.ndim == 2 else np.ascontiguousarray(np.moveaxis(out, 0, -1))


def _axis_taps(n: int, scale: float, offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation along one axis at scale * i + offset, clamped to [0, n - 1]: (i0, i1, weight of i1)."""
    p = np.clip(scale * np.arange(n) + offset, 0, n - 1)
    i0 = np.floor(p).astype(np.intp)
    return i0, np.minimum(i0 + 1, n - 1), (p - i0).astype(np.float32)


def sensor_noise(linear: np.ndarray, rng: np.random.Generator, *, gain: float, read_sigma: float) -> np.ndarray:
    """Linear signal plus zero-mean noise of variance gain * signal + read_sigma^2 (the Poisson-Gaussian model in
    its Gaussian form, as Foi et al. 2008 fit real sensors); float32, not clipped."""
    x = np.asarray(linear, dtype=np.float32)
    sigma = np.sqrt(np.maximum(x, 0.0) * np.float32(gain) + np.float32(read_sigma) ** 2)
    return x + rng.standard_normal(x.shape, dtype=np.float32) * sigma


def add_sensor_noise(rgb_u8: np.ndarray, rng: np.random.Generator, *, gain: float = 0.001,
                     read_sigma: float = 0.002) -> np.ndarray:
    """`sensor_noise` on an 8-bit sRGB image: decoded, noised in linear light, re-encoded."""
    return linear_to_srgb(sensor_noise(srgb_to_linear(rgb_u8), rng, gain=gain, read_sigma=read_sigma))


class AutoExposure:
    """`gain = ae.update(meter)` per frame: the ideal gain target / meter within [min_gain, max_gain], followed in
    log gain by g_k = g_k-1 + alpha (ideal - g_k-1), alpha = 1 - exp(-1 / tau_frames): after a step the gain has
    moved 63 % of the way (in EV) after tau frames. The first frame after `reset` starts settled."""

    def __init__(self, spec: AutoExposureSpec):
        self.spec = spec
        self.alpha = 1.0 if spec.tau_frames == 0 else 1.0 - math.exp(-1.0 / spec.tau_frames)
        self.log_gain: float | None = None

    def reset(self) -> None:
        self.log_gain = None

    def ideal_gain(self, meter: float) -> float:
        s = self.spec
        return s.max_gain if meter <= 0 else float(np.clip(s.target / meter, s.min_gain, s.max_gain))

    def update(self, meter: float) -> float:
        """The gain for this frame, from its meter (`mean_luminance` before any gain)."""
        if not self.spec.enabled:
            return 1.0
        ideal = math.log(self.ideal_gain(meter))
        self.log_gain = ideal if self.log_gain is None else self.log_gain + self.alpha * (ideal - self.log_gain)
        return math.exp(self.log_gain)


def apply_photometric(rgb_u8: np.ndarray, *, effects: CameraEffects, intrinsics: Intrinsics,
                      rng: np.random.Generator, gain: float = 1.0, blur: Blur | None = None) -> np.ndarray:
    """Vignetting, exposure `gain` (from `AutoExposure`), motion `blur` (run frames), saturation, noise and
    8-bit quantisation, in linear light; the input back unchanged when none applies."""
    vig = effects.vignetting.enabled and effects.vignetting.strength > 0
    blur = blur if effects.motion_blur.enabled and blur is not None else Blur()
    moving = blur != Blur()
    noise = effects.noise.enabled and (effects.noise.gain > 0 or effects.noise.read_sigma > 0)
    if not (vig or moving or noise or gain != 1.0):
        return rgb_u8
    x = srgb_to_linear(rgb_u8)
    if vig:
        x = x * vignetting_gain(intrinsics, effects.vignetting.strength)[..., None]
    if gain != 1.0:
        x = x * np.float32(gain)
    if moving:
        x = motion_blur(x, blur, (intrinsics.cx, intrinsics.cy))
    x = np.minimum(x, 1.0)  # the full well saturates
    if noise:
        x = sensor_noise(x, rng, gain=effects.noise.gain, read_sigma=effects.noise.read_sigma)
    return linear_to_srgb(x)


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """JPEG bytes as PIL writes them (4:2:0 chroma below quality 100, as the synth writer always did)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(buf, format="JPEG", quality=int(quality))
    return buf.getvalue()


def encode(rgb: np.ndarray, effects: CameraEffects) -> tuple[bytes, str]:
    """The frame's file bytes and suffix: JPEG at `effects.jpeg_quality`, or PNG when it is None."""
    if effects.jpeg_quality is not None:
        return encode_jpeg(rgb, effects.jpeg_quality), ".jpg"
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue(), ".png"
