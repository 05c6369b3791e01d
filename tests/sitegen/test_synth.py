"""`siteloc synth` end to end on a micro site: determinism, the capture contract, boxes, scans, runs, fallback."""

from __future__ import annotations

import csv
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from pipeline.config import load_config
from pipeline.ingest import run_ingest
from pipeline.io import tables
from pipeline.io.map_yaml import FREE, OCCUPIED, read_map
from pipeline.mapping.occupancy import endpoint_occupied_share
from pipeline.runtime.motion import wrap_angle
from pipeline.sitegen.asset_types import AssetsUnavailableError
from pipeline.sitegen.render import egl_available
from pipeline.sitegen.synth import TIMING_FILE, run_synth
from tests.sitegen.micro import MICRO, captures, digests, micro, synth

pytestmark = pytest.mark.skipif(not egl_available(), reason="no headless EGL context on this machine")

# Every camera effect spelt out and off: the frames synth wrote before camera effects (JPEG 92).
EFFECTS_OFF = {"camera.effects": {"distortion": {"enabled": False}, "vignetting": {"enabled": False},
                                  "auto_exposure": {"enabled": False}, "motion_blur": {"enabled": False},
                                  "noise": {"enabled": False}, "jpeg_quality": 92}}


def test_same_seed_same_bytes_and_another_seed_another_site(site, tmp_path):
    # Rendered here, in one process, with the camera effects explicitly off (the site: absent, the default).
    again = digests(synth(tmp_path / "again", workers=1, preset=micro(**EFFECTS_OFF)))
    assert again == digests(site)
    # Nothing of the effects in the outputs: they are byte for byte what synth wrote before camera effects.
    assert "effects" not in yaml.safe_load((site / "config.yaml").read_text())["preset"]["camera"]
    assert "camera_effects" not in json.loads((site / "synth_report.json").read_text())
    assert "distortion" not in yaml.safe_load((site / "site.yaml").read_text())["camera"]
    assert {"site.yaml", "map.yaml", "map.pgm", "captures.csv", "annotations.json", "contact_sheet.png",
            "config.yaml", "synth_report.json", "runs/query_00/scans.npy"} <= set(again)
    timing = json.loads((site / TIMING_FILE).read_text())
    assert timing["render_images_per_s"] > 0 and timing["wall_time_s"] > 0 and "cores" in timing["machine"]
    assert timing["render_workers"] == 2


def test_a_rendering_pool_fails_with_a_clear_error(tmp_path, monkeypatch):
    from concurrent.futures.process import BrokenProcessPool

    import pipeline.sitegen.render as render
    from pipeline.sitegen.render import RenderError
    from pipeline.sitegen.render_pool import _worker_errors

    def died():
        yield [(0.1, None)]
        raise BrokenProcessPool("a child process terminated abruptly")

    got = _worker_errors(died())
    assert next(got) == [(0.1, None)]
    with pytest.raises(RenderError, match="rendering process died.*--workers 1"):
        next(got)
    monkeypatch.setattr(render, "egl_available", lambda: (False, "cannot create a headless OpenGL 3.3 context"))
    with pytest.raises(RenderError, match="headless OpenGL"):  # before any process is started
        synth(tmp_path / "site", workers=2)
    assert not (tmp_path / "site").exists()


def test_ingest_accepts_the_output_unchanged(site, ingested):
    images = tables.read_table(ingested / "images.parquet", "images").to_pylist()
    rows = captures(site)
    assert len(images) == len(rows) and {r["split"] for r in images} == {"train", "test"}
    boxes = tables.read_table(ingested / "boxes.parquet", "boxes")
    coco = json.loads((site / "annotations.json").read_text())
    assert boxes.num_rows == len(coco["annotations"]) > 0
    report = json.loads((site / "synth_report.json").read_text())
    assert sum(report["boxes_per_class"].values()) == boxes.num_rows
    assert sorted(p.stem for p in (ingested / "runs").glob("*.parquet")) == ["mapping_00", "query_00"]


def test_stops_and_views_as_specified(site):
    preset = micro()
    occ = read_map(site / "map.yaml")
    rows = captures(site)
    by_stop: dict[str, list[dict]] = {}
    for r in rows:
        by_stop.setdefault(r["stop_id"], []).append(r)
    assert all(len(v) == 6 for v in by_stop.values())
    for views in by_stop.values():
        views.sort(key=lambda r: int(r["view"]))
        assert len({(r["x"], r["y"]) for r in views}) == 1
        theta = np.array([float(r["theta"]) for r in views])
        np.testing.assert_allclose(wrap_angle(np.diff(theta)), math.radians(60), atol=1e-5)
    xy = np.array([[float(v[0]["x"]), float(v[0]["y"])] for v in by_stop.values()])
    assert np.all(occ.value_at(xy[:, 0], xy[:, 1]) == FREE)
    gaps = np.sort(np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)), axis=1)[:, 1]
    # A stop every ~spacing metres: each stop's nearest neighbour is about that far (jitter and walls allowed).
    assert 0.3 * preset.stops.spacing < np.median(gaps) < 1.5 * preset.stops.spacing
    from PIL import Image

    with Image.open(site / rows[0]["image"]) as im:
        assert im.size == (96, 72)


def test_boxes_agree_with_a_fresh_instance_buffer(site):
    """Re-render some views and derive each box independently from the id buffer (min/max of its pixels)."""
    from pipeline.sitegen.assets import load_assets
    from pipeline.sitegen.decals import SiteTextures
    from pipeline.sitegen.geometry import object_meshes, structure_meshes
    from pipeline.sitegen.render import Lighting, Renderer
    from pipeline.sitegen.synth import build_scene, intrinsics_of

    preset = micro()
    scene = build_scene(preset, 3, False)
    cls_of = {o.instance_id: o.cls for o in scene.objects}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        library = load_assets(tuple(preset.furnishing.classes))
    coco = json.loads((site / "annotations.json").read_text())
    names = {c["id"]: c["name"] for c in coco["categories"]}
    anns: dict[int, list[dict]] = {}
    for a in coco["annotations"]:
        anns.setdefault(a["image_id"], []).append(a)
    pose_of = {r["image"]: (float(r["x"]), float(r["y"]), preset.camera.height_m, float(r["theta"]))
               for r in captures(site)}
    busiest = sorted(coco["images"], key=lambda im: -len(anns.get(im["id"], [])))[:8]
    textures = SiteTextures(scene, library.textures["poster"], preset.identity.unique_pictures)
    meshes = structure_meshes(scene, library) + object_meshes(scene, library, textures)
    checked = 0
    with Renderer(intrinsics_of(preset)) as renderer:
        renderer.set_scene(meshes)
        for im in busiest:
            _, ids, _ = renderer.render(pose_of[im["file_name"]], Lighting())
            for a in anns[im["id"]]:
                assert names[a["category_id"]] == cls_of[a["instance_id"]]
                ys, xs = np.nonzero(ids == a["instance_id"])
                x, y, w, h = a["bbox"]
                assert (x, y, x + w, y + h) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
                assert w * h >= preset.render.min_box_area_px and 0.25 <= a["visible_share"] <= 1.0
                checked += 1
    assert checked >= 10


def test_scans_hit_the_map_and_runs_flag_their_kidnappings(site, ingested):
    preset = micro()
    occ = read_map(site / "map.yaml")
    for name in ("mapping_00", "query_00"):
        run = tables.read_table(ingested / "runs" / f"{name}.parquet", "runs").to_pydict()
        gt = np.column_stack([run["gt_x"], run["gt_y"], run["gt_theta"]])
        ranges = np.array(run["ranges"], dtype=np.float64)
        assert ranges.shape == (preset.runs.steps_per_run, preset.laser.beams)
        share = endpoint_occupied_share(occ, gt, ranges, run["angle_min"][0], run["angle_increment"][0],
                                        run["range_max"][0], tolerance_cells=1)
        # Returns off the map come from the person and the moved chairs only (noise is 1 cm, within a cell).
        assert share > 0.85
        assert 0 < np.mean(ranges >= preset.laser.range_max) < 0.1  # max-range dropouts
        kidnapped = np.array(run["kidnapped"])
        jumps = np.r_[0.0, np.hypot(*np.diff(gt[:, :2], axis=0).T)]
        expected = preset.runs.kidnaps_per_query_run if name.startswith("query") else 0
        assert kidnapped.sum() == expected and np.all(jumps[kidnapped] > 5.0)
        assert np.all(jumps[~kidnapped] <= 3 * preset.runs.step_m)
        assert all(run["image_id"])


def test_change_keeps_the_building_and_alters_its_contents(site, tmp_path):
    changed = synth(tmp_path / "changed", change=True)
    before, after = (json.loads((p / "synth_report.json").read_text()) for p in (site, changed))
    assert after["changed"] and not before["changed"]
    site_a, site_b = (yaml.safe_load((p / "site.yaml").read_text()) for p in (site, changed))
    assert site_b.pop("name") == site_a.pop("name") + "-changed" and site_a == site_b
    # The same building: stops are resampled on the new map (moved furniture frees or takes space) but stay many.
    assert abs(after["stops"] - before["stops"]) <= 0.2 * before["stops"]
    a, b = (np.asarray(read_map(p / "map.yaml").grid) for p in (site, changed))
    walls_kept = np.mean((a == OCCUPIED) == (b == OCCUPIED))
    assert 0.97 < walls_kept < 1.0  # furniture moved, walls did not
    assert after["objects_per_class"]["poster"] >= before["objects_per_class"]["poster"]
    img = "images/stop0000_v0.jpg"
    assert (changed / img).read_bytes() != (site / img).read_bytes()


def test_missing_meshes_fall_back_to_procedural_shapes_or_fail_clearly(tmp_path, monkeypatch):
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("SITELOC_SH3D_FURNITURE", str(empty))
    monkeypatch.setenv("SITELOC_SH3D_JAR", str(empty))
    monkeypatch.setenv("SITELOC_ASSETS", str(tmp_path / "cache"))
    with pytest.raises(AssetsUnavailableError, match="sweethome3d-furniture"):
        synth(tmp_path / "strict", allow_fallback=False)
    assert not (tmp_path / "strict").exists()
    with pytest.warns(Warning, match="procedural"):
        out = run_synth(micro(**{"stops.spacing": 4.0, "runs.steps_per_run": 4}), outputs={"out": tmp_path / "fb"},
                        seed=1, progress=False)
    report = json.loads((out / "synth_report.json").read_text())
    assert report["assets_procedural"] and report["assets_missing"]
    assert sum(report["boxes_per_class"].values()) > 0
    assert "procedural" in (out / "ATTRIBUTION.md").read_text()


def test_cli_reports_counts_and_refuses_bad_overrides(tmp_path):
    from stages.app import app

    runner = CliRunner()
    res = runner.invoke(app, ["synth", "--preset", "tiny", "--out", str(tmp_path / "x"), "--set", "floor.nope=1"])
    assert res.exit_code == 1 and "floor.nope" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["synth", "--preset", "nowhere", "--out", str(tmp_path / "x")])
    assert res.exit_code == 1 and "tiny" in res.output
    args = ["synth", "--preset", "tiny", "--out", str(tmp_path / "ok"), "--seed", "2"]
    for key, value in {**MICRO, "stops.spacing": 4.0, "runs.steps_per_run": 4}.items():
        args += ["--set", f"{key}={json.dumps(value)}"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "stops" in res.output and "images/s" in res.output and "boxes per class: door" in res.output
    res = runner.invoke(app, args)
    assert res.exit_code == 1 and "--force" in res.output


# A smaller micro site with every camera effect on (`camera.effects: realistic`), the exposure longer so that
# the motion blur of 96-pixel frames is more than a pixel where the robot turns.
EFFECTS_ON = {"stops.spacing": 4.0, "camera.effects": {"base": "realistic", "motion_blur": {"exposure_s": 0.03}}}


@pytest.fixture(scope="module")
def fx_site(tmp_path_factory) -> tuple[Path, list]:
    """The effects-on site, rendered in two processes, and the lighting the parent drew (stops, then runs)."""
    import pipeline.sitegen.synth as synth_module

    drawn, draw = [], synth_module._lighting

    def recorded(*args, **kwargs):
        drawn.append(draw(*args, **kwargs))
        return drawn[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(synth_module, "_lighting", recorded)
        root = synth(tmp_path_factory.mktemp("fx") / "site", preset=micro(**EFFECTS_ON), workers=2)
    return root, drawn


@pytest.fixture(scope="module")
def fx_context(fx_site, tmp_path_factory):
    """A render context of the effects-on site in this process (the workers' code), writing to a scratch root."""
    from pipeline.sitegen.render_pool import open_render_context

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ctx, renderer = open_render_context(micro(**EFFECTS_ON), 3, False, True, tmp_path_factory.mktemp("fxr"))
    yield ctx
    renderer.close()


def test_effects_on_same_bytes_with_one_or_two_workers_and_recorded(fx_site, tmp_path):
    site, _ = fx_site
    again = synth(tmp_path / "again", preset=micro(**EFFECTS_ON), workers=1)
    assert digests(again) == digests(site)
    assert not (site / ".develop").exists() and not (again / ".develop").exists()
    effects = micro(**EFFECTS_ON).camera.effects
    assert effects.noise.enabled and effects.motion_blur.exposure_s == 0.03
    assert yaml.safe_load((site / "config.yaml").read_text())["preset"]["camera"]["effects"] == \
        effects.model_dump(mode="json")
    assert json.loads((site / "synth_report.json").read_text())["camera_effects"] == effects.model_dump(mode="json")


def test_effects_on_site_ingests_unchanged_with_its_lens_in_site_yaml(fx_site, tmp_path):
    from PIL import Image

    from pipeline.io.site import read_site
    from pipeline.sitegen.camera_effects import mean_luminance, site_distortion

    site, _ = fx_site
    camera = read_site(site / "site.yaml").camera
    assert camera.distortion == site_distortion(micro(**EFFECTS_ON).camera.effects.distortion)
    assert camera.distortion.coeffs[0] < 0 and (camera.width, camera.height) == (96, 72)
    ingested = run_ingest(load_config("ci"), inputs={"site": site}, outputs={"out": tmp_path / "ing"}, progress=False)
    images = tables.read_table(ingested / "images.parquet", "images").to_pylist()
    coco = json.loads((site / "annotations.json").read_text())
    assert len(images) == len(captures(site)) == len(coco["images"])
    assert tables.read_table(ingested / "boxes.parquet", "boxes").num_rows == len(coco["annotations"]) > 0
    assert sorted(p.stem for p in (ingested / "runs").glob("*.parquet")) == ["mapping_00", "query_00"]
    # Capture views expose on their own: each settles at the auto-exposure's 18 % grey (without: 8 % to 83 %).
    rows = captures(site)
    for r in rows[:: max(1, len(rows) // 20)]:
        with Image.open(site / r["image"]) as im:
            assert im.size == (96, 72)
            assert mean_luminance(np.asarray(im.convert("RGB"))) == pytest.approx(0.18, abs=0.01), r["image"]


def test_effects_on_boxes_agree_with_a_fresh_distorted_instance_buffer(fx_site, fx_context):
    """Re-render capture views on the larger pinhole canvas, distort the id buffer, derive each box from it."""
    from pipeline.sitegen.camera_effects import apply_distortion
    from pipeline.sitegen.render import Lighting

    site, _ = fx_site
    ctx, preset = fx_context, micro(**EFFECTS_ON)
    k, src = ctx.intrinsics, ctx.source
    pad_u, pad_v = round(src.cx - k.cx), round(src.cy - k.cy)
    assert src.width > k.width and src.height > k.height and pad_u > 0 and pad_v > 0
    coco = json.loads((site / "annotations.json").read_text())
    anns: dict[int, list[dict]] = {}
    for a in coco["annotations"]:
        anns.setdefault(a["image_id"], []).append(a)
    pose_of = {r["image"]: (float(r["x"]), float(r["y"]), preset.camera.height_m, float(r["theta"]))
               for r in captures(site)}
    checked = moved = 0
    for im in sorted(coco["images"], key=lambda im: -len(anns.get(im["id"], [])))[:8]:
        rgb, ids, _ = ctx.renderer.render(pose_of[im["file_name"]], Lighting())
        _, distorted = apply_distortion(rgb, ids, k, preset.camera.effects, source=src)
        pinhole = ids[pad_v:pad_v + k.height, pad_u:pad_u + k.width]  # the undistorted camera's id buffer
        for a in anns[im["id"]]:
            ys, xs = np.nonzero(distorted == a["instance_id"])
            x, y, w, h = a["bbox"]
            assert (x, y, x + w, y + h) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
            assert 0.25 <= a["visible_share"] <= 1.0
            ys, xs = np.nonzero(pinhole == a["instance_id"])
            moved += len(xs) == 0 or (x, y, x + w, y + h) != (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
            checked += 1
    assert checked >= 10 and moved >= checked // 4  # the lens really moves the boxes


def test_run_frames_lag_in_exposure_and_blur_where_the_robot_turns(fx_site, fx_context):
    """Rebuild each run's frames here, one after another, with the lighting the parent drew: the site written
    by two workers is that, byte for byte; the gains lag behind the per-frame ideal; blur lowers the
    horizontal image gradients of turning frames against the same frames developed without blur."""
    from PIL import Image

    from pipeline.sitegen.camera_effects import AutoExposure
    from pipeline.sitegen.render_pool import View, develop_frames, render_views
    from pipeline.sitegen.synth import run_blurs

    site, drawn = fx_site
    ctx, preset = fx_context, micro(**EFFECTS_ON)
    report = json.loads((site / "synth_report.json").read_text())
    spec = preset.camera.effects.auto_exposure
    turning = lagging = 0
    for k, name in enumerate(report["runs"]):
        with (site / "runs" / name / "trajectory.csv").open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        gt = np.array([[float(r["gt_x"]), float(r["gt_y"]), float(r["gt_theta"])] for r in rows])
        run = type("Run", (), {"t": np.array([float(r["t"]) for r in rows]), "gt": gt,
                               "kidnapped": np.array([r["kidnapped"] == "1" for r in rows])})
        blurs = run_blurs(run, ctx.intrinsics, preset.camera.effects.motion_blur)
        views = [View((*gt[i, :2], preset.camera.height_m, gt[i, 2]), f"{name}/{i:04d}.jpg", False, frame=(1, 0, k, i),
                      blur=blurs[i], lagged=True) for i in range(len(rows))]
        meters = [r.meter for r in render_views(ctx, drawn[report["stops"] + k], views)]
        ae = AutoExposure(spec)
        gains = [ae.update(m) for m in meters]
        lagging += sum(abs(g / AutoExposure(spec).ideal_gain(m) - 1) > 0.02 for g, m in zip(gains, meters, strict=True))
        develop_frames(ctx, views, gains)
        for v, r in zip(views, rows, strict=True):
            assert (ctx.root / v.rel).read_bytes() == (site / r["image"]).read_bytes(), r["image"]
        sharp = [View(v.pose, v.rel.replace(".jpg", "_sharp.jpg"), False, frame=v.frame, lagged=True) for v in views]
        render_views(ctx, drawn[report["stops"] + k], sharp)
        develop_frames(ctx, sharp, gains)
        for v, s, b in zip(views, sharp, blurs, strict=True):
            if abs(b.shift[0]) < 1.0:
                continue
            blurred, still = (np.asarray(Image.open(ctx.root / x.rel).convert("L"), float) for x in (v, s))
            ex, ex0 = (float(np.mean(np.diff(img, axis=1) ** 2)) for img in (blurred, still))
            assert ex < 0.9 * ex0, (v.rel, b)
            turning += 1
    assert turning >= 3 and lagging >= 2
