"""Camera effects against independent references: the noise model's variance, the cos^4 vignetting formula,
distortion round trips and a moved dot, streak lengths, the auto-exposure lag, JPEG quality, all-off identity."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from pipeline.errors import ConfigError
from pipeline.io.site import Distortion
from pipeline.sitegen.camera import Intrinsics
from pipeline.sitegen.camera_effects import (
    AutoExposure,
    AutoExposureSpec,
    Blur,
    CameraEffects,
    DistortionSpec,
    MotionBlurSpec,
    add_sensor_noise,
    apply_distortion,
    apply_photometric,
    blur_from_motion,
    distort_image,
    distort_points,
    encode,
    encode_jpeg,
    frame_rng,
    linear_to_srgb,
    mean_luminance,
    motion_blur,
    sensor_noise,
    site_distortion,
    source_intrinsics,
    srgb_to_linear,
    undistort_points,
    vignetting_gain,
)

K = Intrinsics.from_hfov(160, 120, math.radians(70.0))
COEFFS = (-0.05, 0.01, 0.001, -0.0005, 0.002)


def scene(seed: int = 0, k: Intrinsics = K) -> np.ndarray:
    """A smooth, textured test frame (JPEG-friendly, no flat areas)."""
    v, u = np.mgrid[0:k.height, 0:k.width]
    rng = np.random.default_rng(seed)
    base = 128 + 60 * np.sin(u / 7.0)[..., None] * np.cos(v / 5.0)[..., None] * rng.uniform(0.5, 1.0, 3)
    return np.clip(base + rng.normal(0, 4, (k.height, k.width, 3)), 0, 255).astype(np.uint8)


def test_srgb_round_trip_is_exact_for_every_8_bit_value():
    values = np.arange(256, dtype=np.uint8)
    assert np.array_equal(linear_to_srgb(srgb_to_linear(values)), values)
    assert srgb_to_linear(np.uint8(255)) == pytest.approx(1.0) and srgb_to_linear(np.uint8(0)) == 0.0
    assert srgb_to_linear(np.uint8(128)) == pytest.approx(0.21586, abs=1e-5)  # IEC 61966-2-1 table value


@pytest.mark.parametrize("signal", [0.05, 0.3])
def test_noise_variance_follows_the_poisson_gaussian_model(signal):
    gain, read = 0.004, 0.01
    flat = np.full((400, 500), signal, np.float32)
    noisy = sensor_noise(flat, np.random.default_rng(1), gain=gain, read_sigma=read)
    want = gain * signal + read**2
    n = flat.size
    assert abs(float(noisy.mean()) - signal) < 4 * math.sqrt(want / n)
    assert float(noisy.var()) == pytest.approx(want, rel=4 * math.sqrt(2 / n))  # 4 standard errors of a variance
    assert np.array_equal(sensor_noise(flat, np.random.default_rng(1), gain=0, read_sigma=0), flat)


def test_noise_on_8_bit_frames_keeps_the_mean_and_is_seeded():
    grey = np.full((200, 200, 3), 118, np.uint8)
    a = add_sensor_noise(grey, np.random.default_rng(5))
    assert a.dtype == np.uint8 and a.std() > 1.0 and abs(float(a.mean()) - 118) < 0.2
    assert np.array_equal(a, add_sensor_noise(grey, np.random.default_rng(5)))
    assert not np.array_equal(a, add_sensor_noise(grey, np.random.default_rng(6)))


def test_vignetting_equals_the_cos4_formula_at_centre_edge_and_corner():
    k = Intrinsics(101, 81, 60.0, 55.0, 50.0, 40.0)  # principal point on a pixel centre
    g = vignetting_gain(k, 0.7)
    for u, v in ((50, 40), (100, 40), (50, 0), (100, 80), (0, 0)):
        theta = math.atan(math.hypot((u - k.cx) / k.fx, (v - k.cy) / k.fy))
        assert g[v, u] == pytest.approx(1 - 0.7 * (1 - math.cos(theta) ** 4), abs=1e-6), (u, v)
    assert g[40, 50] == 1.0 and g.min() == g[0, 0] == g[80, 100]
    assert np.all(vignetting_gain(k, 0.0) == 1.0)


def test_undistort_inverts_distort_to_a_micro_pixel_over_the_image():
    v, u = np.mgrid[-0.5:K.height:2.5, -0.5:K.width:2.5]
    p = np.column_stack([u.ravel(), v.ravel()])
    d = distort_points(p, K, COEFFS)
    assert np.max(np.abs(d - p)) > 2.0  # the model really moves points
    np.testing.assert_allclose(undistort_points(d, K, COEFFS), p, atol=1e-6)
    np.testing.assert_allclose(distort_points(undistort_points(p, K, COEFFS), K, COEFFS), p, atol=1e-6)
    # The forward model by hand at one point: normalised (0.4, -0.3).
    x, y = 0.4, -0.3
    k1, k2, p1, p2, k3 = COEFFS
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd, yd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    got = distort_points([[x * K.fx + K.cx, y * K.fy + K.cy]], K, COEFFS)[0]
    np.testing.assert_allclose(got, [xd * K.fx + K.cx, yd * K.fy + K.cy], atol=1e-9)


def test_a_folding_model_is_a_config_error():
    with pytest.raises(ConfigError, match="cannot be inverted"):
        undistort_points([[K.cx + 0.5 * K.fx, K.cy]], K, (-2.0, 0.0, 0.0, 0.0, 0.0))  # r_d = 0.5 > max r(1 - 2r^2)


def test_distort_image_moves_a_dot_where_distort_points_says():
    v, u = np.mgrid[0:K.height, 0:K.width]
    q = np.array([20.0, 15.0])  # near the top-left corner, where barrel distortion moves points most
    dot = 1000.0 * np.exp(-((u - q[0]) ** 2 + (v - q[1]) ** 2) / (2 * 1.5**2))
    strong = (-0.2, 0.03, 0.002, -0.001, 0.0)
    out = distort_image(dot, K, strong)
    centroid = np.array([(out * u).sum(), (out * v).sum()]) / out.sum()
    want = distort_points(q, K, strong)[0]
    assert np.hypot(*(want - q)) > 4.0
    assert np.hypot(*(centroid - want)) < 0.1


def test_nearest_mode_keeps_ids_from_the_input_and_a_margin_leaves_no_hole():
    rng = np.random.default_rng(2)
    ids = np.kron(rng.integers(1, 40, (12, 16)), np.ones((10, 10), int)).astype(np.uint32)  # 160 x 120 blocks
    out = distort_image(ids, K, COEFFS, nearest=True)
    assert out.dtype == np.uint32 and set(np.unique(out)) <= set(np.unique(ids)) | {0}
    assert out[0, 0] == 0  # barrel: the corner's ray is outside the pinhole render
    src = source_intrinsics(K, COEFFS)
    assert src.width > K.width and src.height > K.height and src.fx == K.fx
    big = np.ones((src.height, src.width), np.uint32)
    assert np.all(distort_image(big, K, COEFFS, nearest=True, source=src) == 1)
    rgb = scene(k=src)
    warped, warped_ids = apply_distortion(rgb, big, K, CameraEffects(), source=src)
    assert warped.shape == (K.height, K.width, 3) and warped.dtype == np.uint8 and warped.min() > 0
    assert np.all(warped_ids == 1)


def test_motion_blur_streak_length_and_energy():
    img = np.zeros((41, 61, 1), np.float32)
    img[20, 30] = 1.0
    out = motion_blur(img, Blur((4.0, 0.0)))
    assert np.count_nonzero(out > 1e-7) == 5 and np.allclose(out[20, 28:33, 0], 0.2)
    assert out.sum() == pytest.approx(1.0, abs=1e-6)
    diag = motion_blur(img, Blur((3.0, -3.0)))
    assert diag.sum() == pytest.approx(1.0, abs=1e-6)
    v, u = np.nonzero(diag[..., 0] > 0)
    w = diag[v, u, 0]
    mean = np.array([(w * u).sum(), (w * v).sum()]) / w.sum()
    cov = np.cov(np.stack([u, v]), aweights=w)
    evals, evecs = np.linalg.eigh(cov)
    assert np.allclose(mean, [30, 20], atol=1e-6) and evals[1] > 10 * evals[0]
    assert abs(evecs[:, 1] @ [1 / math.sqrt(2), -1 / math.sqrt(2)]) > 0.999  # along the motion (3, -3)
    # Forward motion: the definition evaluated on the continuous blob (no resampling) is the reference; a blob
    # 20 px right of the centre streaks along x by 0.2 * 20 = 4 px; taps: the farthest pixel moves 10 px.
    v, u = np.mgrid[0:41, 0:61].astype(float)

    def blob(x, y):
        return np.exp(-((x - 30.0) ** 2 + (y - 20.0) ** 2) / (2 * 2.0**2))

    zoom = motion_blur(blob(u, v)[..., None].astype(np.float32), Blur(zoom=0.2), centre=(10.0, 20.0))[..., 0]
    ts = np.linspace(-0.5, 0.5, math.ceil(0.2 * 50) + 1)
    want = np.mean([blob(u - t * 0.2 * (u - 10.0), v - t * 0.2 * (v - 20.0)) for t in ts], axis=0)
    assert np.max(np.abs(want - blob(u, v))) > 0.15  # the streak lowers the peak by 17 %
    assert np.max(np.abs(zoom - want)) < 0.02
    flat = np.full((41, 61, 3), 0.25, np.float32)
    assert np.allclose(motion_blur(flat, Blur((2.5, 1.0), 0.1)), 0.25, atol=1e-6)  # surfaces keep their radiance
    np.testing.assert_allclose(motion_blur(img, Blur((0.4, 0.0)))[20, 29:32, 0], [0.1, 0.8, 0.1], atol=1e-6)
    assert motion_blur(img, Blur()) is img


def test_blur_from_motion_uses_the_yaw_rate_and_the_forward_speed():
    spec = MotionBlurSpec(exposure_s=0.02, forward_depth_m=4.0)
    b = blur_from_motion(K, spec, yaw_rate=1.0, speed=0.8)
    assert b.shift == pytest.approx((K.fx * 0.02, 0.0)) and b.zoom == pytest.approx(0.8 * 0.02 / 4.0)
    assert blur_from_motion(K, spec.model_copy(update={"enabled": False}), yaw_rate=1.0, speed=1.0) == Blur()


def test_auto_exposure_lags_by_its_time_constant():
    spec = AutoExposureSpec(target=0.2, tau_frames=4.0, min_gain=0.1, max_gain=10.0)
    ae = AutoExposure(spec)
    assert ae.update(0.1) == pytest.approx(2.0)  # settled on the first frame
    gains = [ae.update(0.4) for _ in range(40)]  # the scene gets 4x brighter: ideal gain 0.5
    step = math.log(0.5) - math.log(2.0)
    moved = [(math.log(g) - math.log(2.0)) / step for g in gains]
    assert moved[3] == pytest.approx(1 - math.exp(-1), abs=1e-9)  # 63 % after tau = 4 frames
    assert moved[7] == pytest.approx(1 - math.exp(-2), abs=1e-9)
    assert gains[-1] == pytest.approx(0.5, rel=1e-3)
    assert AutoExposure(spec.model_copy(update={"max_gain": 3.0})).update(0.01) == pytest.approx(3.0)
    assert AutoExposure(spec.model_copy(update={"enabled": False})).update(0.01) == 1.0
    assert AutoExposure(spec.model_copy(update={"tau_frames": 0.0})).update(0.05) == pytest.approx(4.0)


def test_photometric_gain_brings_the_meter_to_the_target():
    frame = scene()
    effects = CameraEffects.off()
    gain = AutoExposure(AutoExposureSpec(target=0.18)).update(mean_luminance(frame))
    out = apply_photometric(frame, effects=effects, intrinsics=K, rng=frame_rng(0, 1), gain=gain)
    assert mean_luminance(out) == pytest.approx(0.18, rel=0.02)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(255.0**2 / np.mean((a.astype(float) - b.astype(float)) ** 2))


def test_jpeg_quality_bounds_the_error_and_the_size():
    frame = scene()
    sizes = {}
    for q in (30, 80, 95):
        data = encode_jpeg(frame, q)
        back = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
        assert back.shape == frame.shape and psnr(back, frame) > {30: 28, 80: 32, 95: 36}[q], q
        sizes[q] = len(data)
    assert sizes[30] < sizes[80] < sizes[95]
    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="JPEG", quality=92)  # the synth writer's call
    assert encode_jpeg(frame, 92) == buf.getvalue()
    png, suffix = encode(frame, CameraEffects(jpeg_quality=None))
    assert suffix == ".png" and np.array_equal(np.asarray(Image.open(io.BytesIO(png))), frame)


def test_all_effects_off_give_the_input_back_bit_for_bit():
    frame, ids = scene(), np.arange(K.width * K.height, dtype=np.uint32).reshape(K.height, K.width)
    off = CameraEffects.off()
    rgb, same_ids = apply_distortion(frame, ids, K, off)
    assert rgb is frame and same_ids is ids
    out = apply_photometric(frame, effects=off, intrinsics=K, rng=frame_rng(0), blur=Blur((5.0, 0.0), 0.01))
    assert np.array_equal(out, frame)
    assert off.jpeg_quality == 92 and site_distortion(off.distortion) is None
    zeroed = CameraEffects(noise={"gain": 0.0, "read_sigma": 0.0}, vignetting={"strength": 0.0},
                           motion_blur={"exposure_s": 0.0}, distortion={"k1": 0.0, "k2": 0.0})
    assert np.array_equal(apply_photometric(frame, effects=zeroed, intrinsics=K, rng=frame_rng(0)), frame)
    assert apply_distortion(frame, ids, K, zeroed)[1] is ids


def test_same_seed_same_bytes_and_each_effect_changes_the_frame():
    frame = scene()
    on = CameraEffects()

    def run(seed, effects=on):
        rgb, _ = apply_distortion(frame, None, K, effects)
        blur = blur_from_motion(K, effects.motion_blur, yaw_rate=0.8, speed=0.8)
        out = apply_photometric(rgb, effects=effects, intrinsics=K, rng=frame_rng(seed, 3, 7), gain=1.3, blur=blur)
        return encode(out, effects)[0]

    assert run(4) == run(4) and run(4) != run(5)
    for section in ("distortion", "vignetting", "motion_blur", "noise"):
        one = CameraEffects.off(jpeg_quality=None).model_copy(update={section: getattr(on, section)})
        assert run(4, one) != run(4, CameraEffects.off(jpeg_quality=None)), section


def test_site_distortion_is_the_site_yaml_camera_model():
    d = site_distortion(DistortionSpec(k1=-0.1, k2=0.02, p1=0.001))
    assert d == Distortion(coeffs=(-0.1, 0.02, 0.001, 0.0, 0.0))
    assert d.model_dump(mode="json") == {"model": "plumb_bob", "coeffs": [-0.1, 0.02, 0.001, 0.0, 0.0]}
    assert site_distortion(DistortionSpec(enabled=False)) is None


def test_a_gain_range_upside_down_is_refused():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="min_gain 4.0 is above max_gain 2.0"):
        AutoExposureSpec(min_gain=4.0, max_gain=2.0)


def test_the_lens_measures_a_pinhole_rectangle_in_distorted_pixels():
    """boxes.Lens against counting: a rectangle of the pinhole render resampled through the lens (nearest)."""
    from pipeline.sitegen.boxes import Lens

    src = source_intrinsics(K, COEFFS)
    lens = Lens.of(K, COEFFS, src)
    assert lens.area(-1e9, 1e9, -1e9, 1e9) == pytest.approx(K.width * K.height, rel=0.01)  # the whole image
    v, u = np.mgrid[0:src.height, 0:src.width]
    for u1, u2, v1, v2 in ((60.0, 100.0, 40.0, 80.0), (-5.0, 40.0, -5.0, 30.0), (150.0, 400.0, 100.0, 400.0)):
        inside = ((u >= u1) & (u <= u2) & (v >= v1) & (v <= v2)).astype(np.uint8)
        count = int(distort_image(inside, K, COEFFS, nearest=True, source=src).sum())
        assert count > 100 and lens.area(u1, u2, v1, v2) == pytest.approx(count, rel=0.03), (u1, v1)
    flat = Lens.of(K, (0.0,) * 5, K)  # no distortion: one pixel per pixel
    assert flat.area(10.2, 20.7, 5.0, 9.0) == 10 * 5
    assert lens.area(1e4, 2e4, 0, 10) == 0.0


def test_run_blurs_follow_the_ground_truth_motion_and_stop_at_a_kidnapping():
    from types import SimpleNamespace

    from pipeline.sitegen.synth import run_blurs

    # Steps: straight 0.4 m, then turning left 0.2 rad, then a teleport into frame 3, then 0.4 m straight.
    gt = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.8, 0.0, 0.2], [9.0, 9.0, 1.0],
                   [9.0 + 0.4 * math.cos(1.0), 9.0 + 0.4 * math.sin(1.0), 1.0]])
    run = SimpleNamespace(t=0.5 * np.arange(5), gt=gt, kidnapped=np.array([False, False, False, True, False]))
    spec = MotionBlurSpec(exposure_s=0.02, forward_depth_m=4.0)
    b = run_blurs(run, K, spec)
    assert b[0] == blur_from_motion(K, spec, yaw_rate=0.0, speed=0.8)  # forward only: a zoom, no shift
    assert b[0].shift == (0.0, 0.0) and b[0].zoom == pytest.approx(0.8 * 0.02 / 4.0)
    assert b[1].shift[0] == pytest.approx(K.fx * 0.2 * 0.02)  # mean of 0 and 0.4 rad/s: left turn, scene moves right
    forward_2 = 0.4 * math.cos(0.0) / 0.5
    want = blur_from_motion(K, spec, yaw_rate=0.4, speed=forward_2)  # the teleport after it does not count
    assert b[2].shift == pytest.approx(want.shift) and b[2].zoom == pytest.approx(want.zoom)
    want = blur_from_motion(K, spec, yaw_rate=0.0, speed=0.8)  # after the teleport: the next step alone
    for blur in b[3:]:
        assert blur.shift == pytest.approx(want.shift, abs=1e-9) and blur.zoom == pytest.approx(want.zoom)
    alone = SimpleNamespace(t=run.t[:3], gt=gt[:3], kidnapped=np.array([False, True, True]))
    assert run_blurs(alone, K, spec)[1] == Blur()  # between two teleports: no motion
    assert run_blurs(run, K, spec.model_copy(update={"enabled": False})) == [Blur()] * 5


def test_camera_effects_in_a_preset_default_off_and_override_one_at_a_time():
    from pipeline.sitegen.presets import SitePreset, load_site_preset

    assert load_site_preset("tiny").camera.effects == CameraEffects.off()
    one = load_site_preset("tiny", {"camera.effects.noise.enabled": True}).camera.effects
    assert one == CameraEffects.off().model_copy(update={"noise": CameraEffects().noise})  # the noise alone
    assert load_site_preset("tiny", {"camera.effects": "realistic"}).camera.effects == CameraEffects()
    most = load_site_preset("tiny", {"camera.effects.base": "realistic", "camera.effects.noise.enabled": False,
                                     "camera.effects.jpeg_quality": None}).camera.effects
    assert not most.noise.enabled and most.distortion.enabled and most.auto_exposure.enabled
    assert most.jpeg_quality is None
    for preset in (load_site_preset("tiny", {"camera.effects.distortion": {"enabled": True, "k1": -0.1}}),
                   load_site_preset("tiny", {"camera.effects": "realistic"})):
        assert SitePreset.model_validate(preset.model_dump(mode="json")) == preset  # config.yaml reads back
    with pytest.raises(ConfigError, match="base must be one of off, realistic"):
        load_site_preset("tiny", {"camera.effects": "vivid"})
    with pytest.raises(ConfigError, match="camera.effects.nois"):
        load_site_preset("tiny", {"camera.effects.nois.enabled": True})
