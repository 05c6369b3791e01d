"""`ingest-colmap`: a moved and scaled model comes back onto the map through three anchors, the round trip through
`export-colmap` reproduces captures.csv, incomplete stops are reported, and bad input leaves no output."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import typer
import yaml
from PIL import Image
from typer.testing import CliRunner

from pipeline.colmap.export import run_export_colmap
from pipeline.colmap.ingest import run_ingest_colmap
from pipeline.errors import InputError, OutputExistsError
from pipeline.ingest import run_ingest, validate_site_dir
from pipeline.io.site import Distortion, read_site, write_site
from stages.colmap import export_colmap, ingest_colmap
from tests.colmap import CFG, angle_diff, random_sim3, read_rows, stops_of, trivial_frame_model, write_anchors
from tests.fixtures.capture_site import site_yaml, write_capture_site

ANCHORS = ["images/s0_v0.png", "images/s1_v3.png", "images/s2_v4.png"]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    return write_capture_site(tmp_path_factory.mktemp("ingest_colmap") / "site", with_run=False)


@pytest.fixture(scope="module")
def model_dir(site) -> Path:
    """export-colmap of the site: a rig of six cameras, one frame per stop, in map coordinates."""
    return run_export_colmap(CFG, inputs={"site": site}, outputs={"out": site.parent / "model"})


def ingest(model: Path, site: Path, out: Path, anchors: Path | None = None, **kw) -> Path:
    inputs = {"model": model, "images": site / "images", "map": site / "map.yaml", "anchors": anchors}
    return run_ingest_colmap(CFG, inputs=inputs, outputs={"out": out}, progress=False, **kw)


def write_model(rec: pycolmap.Reconstruction, path: Path, text: bool = False) -> Path:
    path.mkdir(parents=True)
    (rec.write_text if text else rec.write)(str(path))
    return path


def assert_poses_match(got: dict, want: dict, pos_m: float, head_deg: float) -> None:
    assert set(got) == set(want)
    assert stops_of(got) == stops_of(want)
    for name, r in want.items():
        assert math.hypot(got[name]["x"] - r["x"], got[name]["y"] - r["y"]) <= pos_m, name
        assert math.degrees(angle_diff(got[name]["theta"], r["theta"])) <= head_deg, name


@pytest.mark.parametrize(
    ("grouping", "seed", "text"), [("rig", 0, False), ("rig", 1, True), ("positions", 2, False), ("positions", 3, True)]
)
def test_a_random_similarity_is_undone_by_three_anchors(site, model_dir, tmp_path, grouping, seed, text):
    rec = pycolmap.Reconstruction(str(model_dir)) if grouping == "rig" else trivial_frame_model(site)
    sim = random_sim3(np.random.default_rng(seed))
    rec.transform(sim)  # pycolmap moves every image (and frame) by new_from_old
    moved = write_model(rec, tmp_path / "moved", text=text)
    anchors = write_anchors(tmp_path / "anchors.csv", site, ANCHORS)
    out = ingest(moved, site, tmp_path / "out", anchors)

    assert_poses_match(read_rows(out / "captures.csv"), read_rows(site / "captures.csv"), 0.01, 0.5)
    rep = json.loads((out / "report.json").read_text())
    assert rep["grouping"] == ("rig frames" if grouping == "rig" else "positions within 0.05 m")
    assert rep["stops"] == 4 and rep["images"] == 24 and rep["stops_left_out"] == []
    a = rep["alignment"]
    assert a["scale"] == pytest.approx(1.0 / float(sim.scale), rel=1e-9)
    assert a["position_error_m"]["max"] < 1e-6 and a["heading_error_deg"]["max"] < 1e-3
    assert [r["image"] for r in a["anchors"]] == [n.removeprefix("images/") for n in ANCHORS]
    assert yaml.safe_load((out / "site.yaml").read_text())["camera"] == site_yaml()["camera"]
    assert (out / "report.md").read_text().startswith(f"# ingest-colmap report: {out.name}")
    assert yaml.safe_load((out / "config.yaml").read_text())["stage"] == "ingest_colmap"
    # The output is a capture directory that ingest accepts unchanged.
    validate_site_dir(out, CFG.ingest, progress=False)
    ingested = run_ingest(CFG, inputs={"site": out}, outputs={"out": tmp_path / "ingested"}, progress=False)
    assert json.loads((ingested / "report.json").read_text())["stops"] == 4


def test_noisy_anchors_and_a_captures_csv_as_anchors(site, model_dir, tmp_path):
    rec = pycolmap.Reconstruction(str(model_dir))
    rec.transform(random_sim3(np.random.default_rng(11)))
    moved = write_model(rec, tmp_path / "moved")
    rng = np.random.default_rng(5)
    anchors = write_anchors(
        tmp_path / "noisy.csv",
        site,
        ANCHORS + ["images/s3_v1.png"],
        x=float(rng.normal(scale=0.003)),
        y=float(rng.normal(scale=0.003)),
    )
    out = ingest(moved, site, tmp_path / "out", anchors)
    assert_poses_match(read_rows(out / "captures.csv"), read_rows(site / "captures.csv"), 0.01, 0.5)
    # Every row of another site's captures.csv is an anchor (stop_id, view, room, area are ignored).
    out = ingest(moved, site, tmp_path / "out2", site / "captures.csv")
    assert len(json.loads((out / "report.json").read_text())["alignment"]["anchors"]) == 24


def test_export_then_ingest_in_map_frame_reproduces_captures(site, model_dir, tmp_path):
    out = ingest(model_dir, site, tmp_path / "out", in_map_frame=True, name="tiny")
    got, want = read_rows(out / "captures.csv"), read_rows(site / "captures.csv")
    assert_poses_match(got, want, 1e-6, math.degrees(1e-6))
    for name, r in want.items():
        assert got[name]["view"] == r["view"]
        assert abs(got[name]["x"] - r["x"]) < 1e-6 and abs(got[name]["y"] - r["y"]) < 1e-6
    rep = json.loads((out / "report.json").read_text())
    assert rep["site"] == "tiny" and rep["alignment"]["method"] == "none (--in-map-frame)"
    assert rep["camera_z_m"] == {"min": pytest.approx(1.2), "max": pytest.approx(1.2)}
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(n.removeprefix("images/") for n in want)
    validate_site_dir(out, CFG.ingest, progress=False)
    # Anchors with --in-map-frame are not fitted but checked.
    out = ingest(
        model_dir,
        site,
        tmp_path / "checked",
        write_anchors(tmp_path / "a.csv", site, ANCHORS[:1], theta=0.1),
        in_map_frame=True,
    )
    rep = json.loads((out / "report.json").read_text())
    assert rep["alignment"]["heading_error_deg"]["max"] == pytest.approx(math.degrees(0.1), abs=1e-4)
    assert any("anchor heading error" in w for w in rep["warnings"])


@pytest.mark.parametrize("coeffs", [(-0.05, 0.01, 0.001, -0.002, 0.0), (-0.05, 0.01, 0.0, 0.0, 0.003)])
def test_a_distorted_camera_goes_out_and_comes_back_with_its_coefficients(site, tmp_path, coeffs):
    distorted = tmp_path / "site"
    shutil.copytree(site, distorted)
    plain = read_site(site / "site.yaml")
    camera = plain.camera.model_copy(update={"distortion": Distortion(coeffs=coeffs)})
    write_site(distorted / "site.yaml", plain.model_copy(update={"camera": camera}))
    model = run_export_colmap(CFG, inputs={"site": distorted}, outputs={"out": tmp_path / "model"})
    cam = pycolmap.Reconstruction(str(model)).camera(1)
    if coeffs[4] == 0:
        assert cam.model_name == "OPENCV"
        np.testing.assert_allclose(cam.params, [40.0, 40.0, 32.5, 24.5, *coeffs[:4]])
    else:
        assert cam.model_name == "FULL_OPENCV"
        np.testing.assert_allclose(cam.params, [40.0, 40.0, 32.5, 24.5, *coeffs, 0.0, 0.0, 0.0])
    out = ingest(model, distorted, tmp_path / "out", in_map_frame=True, name="tiny")
    back = read_site(out / "site.yaml")
    assert back.camera == camera and back.camera.distortion.coeffs == coeffs


def test_radial_models_become_a_plumb_bob_distortion(site, tmp_path):
    model = write_model(trivial_frame_model(site, model="SIMPLE_RADIAL"), tmp_path / "model")  # k = 0.01
    back = read_site(ingest(model, site, tmp_path / "out", in_map_frame=True) / "site.yaml")
    assert (back.camera.fx, back.camera.fy, back.camera.cx, back.camera.cy) == (40.0, 40.0, 32.0, 24.0)
    assert back.camera.distortion == Distortion(coeffs=(0.01, 0.0, 0.0, 0.0, 0.0))
    pinhole = write_model(trivial_frame_model(site), tmp_path / "pinhole")
    out = ingest(pinhole, site, tmp_path / "out2", in_map_frame=True)
    assert read_site(out / "site.yaml").camera.distortion is None
    assert "distortion" not in (out / "site.yaml").read_text()


def test_incomplete_and_inconsistent_stops_are_reported_not_written(site, tmp_path):
    adjust = {
        "images/s1_v2.png": {"theta": math.radians(10.0)},  # disagrees with the rig
        "images/s2_v5.png": {"x": 0.3},  # its own stop of one image: both stops lack views
    }
    rec = trivial_frame_model(site, adjust=adjust)
    rec.deregister_frame(rec.find_image_with_name("s0_v3.png").frame_id)  # not written: stop s0 lacks view 3
    out = ingest(write_model(rec, tmp_path / "model"), site, tmp_path / "out", in_map_frame=True)
    rep = json.loads((out / "report.json").read_text())
    left = {s["images"][0]: s for s in rep["stops_left_out"]}
    assert left["s0_v0.png"]["reasons"] == ["5 images, the rig has 6 views", "views [3] missing"]
    assert left["s1_v0.png"]["reasons"] == ["headings disagree with the rig yaw offsets by 8.3 deg (tolerance 3.0 deg)"]
    assert left["s2_v0.png"]["reasons"] == ["5 images, the rig has 6 views", "views [5] missing"]
    assert left["s2_v5.png"]["reasons"][0] == "1 images, the rig has 6 views"
    assert rep["images_left_out"] == [] and rep["model"]["images"] == 23
    assert rep["stops"] == 1 and {r["image"][7:9] for r in read_rows(out / "captures.csv").values()} == {"s3"}
    assert any("4 of 5 stops left out" in w for w in rep["warnings"])
    validate_site_dir(out, CFG.ingest, progress=False)
    # A stop inside a wall or off the map is left out too (ingest would refuse it).
    rec = trivial_frame_model(
        site,
        adjust={f"images/s3_v{v}.png": {"x": 2.0} for v in range(6)}
        | {f"images/s0_v{v}.png": {"x": -0.95} for v in range(6)},
    )
    out = ingest(write_model(rec, tmp_path / "model2"), site, tmp_path / "out2", in_map_frame=True)
    reasons = {s["images"][0]: s["reasons"] for s in json.loads((out / "report.json").read_text())["stops_left_out"]}
    assert reasons == {"s0_v0.png": ["inside a wall (occupied map cell)"], "s3_v0.png": ["outside the map"]}


def test_an_upside_down_model_in_the_map_frame_is_flagged(site, model_dir, tmp_path):
    rec = pycolmap.Reconstruction(str(model_dir))
    flip = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(np.array([math.pi, 0.0, 0.0])), np.array([0.0, 4.0, 0.0]))
    rec.transform(flip)  # (x, y, z) -> (x, 4 - y, -z): on the map, but z points down
    with pytest.raises(InputError) as err:
        ingest(write_model(rec, tmp_path / "flipped"), site, tmp_path / "out", in_map_frame=True)
    assert "no complete stop (4 found, grouped by rig frames)" in str(err.value)
    assert "headings disagree with the rig yaw offsets" in str(err.value)  # a mirror turns the rig clockwise
    assert "24 of 24 cameras are upside down in the map frame" in str(err.value)
    assert_no_output(tmp_path / "out")


def _replace(path: Path, text: str) -> None:
    path.write_text(text)


def _unsupported_camera(w: dict) -> None:
    shutil.rmtree(w["model"])
    write_model(trivial_frame_model(w["site"], model="SIMPLE_RADIAL_FISHEYE"), w["model"])


def _rational_camera(w: dict) -> None:
    rec = pycolmap.Reconstruction(str(w["model"]))
    for cam in rec.cameras.values():
        cam.model = "FULL_OPENCV"
        cam.params = [40.0, 40.0, 32.5, 24.5, -0.05, 0.01, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0]  # k4 = 0.1
    rec.write(str(w["model"]))


def _mirrored_anchors(w: dict) -> None:
    rows = read_rows(w["site"] / "captures.csv")  # y measured downwards, as image rows are
    lines = [f"{n},{rows[n]['x']},{4.0 - rows[n]['y']},{-rows[n]['theta']}" for n in ANCHORS]
    w["anchors"].write_text("image,x,y,theta\n" + "\n".join(lines) + "\n")


def _nested_model(w: dict) -> None:
    inner = w["model"].parent / "inner"
    w["model"].rename(inner)
    w["model"].mkdir()
    inner.rename(w["model"] / "0")  # COLMAP's sparse/ holds models 0, 1, ...


def _small_image(w: dict) -> None:
    Image.new("RGB", (32, 32)).save(w["images"] / "s0_v1.png")


# (name, how to break the inputs, substrings the error must contain)
BREAKAGES = [
    ("model_missing", lambda w: shutil.rmtree(w["model"]), ["COLMAP model not found", "not a directory"]),
    (
        "model_files_missing",
        lambda w: (w["model"] / "images.bin").unlink(),
        ["not a COLMAP model", "missing images.bin or .txt"],
    ),
    ("model_nested", _nested_model, ["missing cameras.bin or .txt", "pass one model folder, e.g. ", "model/0"]),
    (
        "model_unreadable",
        lambda w: (w["model"] / "cameras.bin").write_bytes(b"garbage" * 10),
        ["unreadable COLMAP model", "pycolmap cannot read it"],
    ),
    (
        "camera_unsupported",
        _unsupported_camera,
        [
            "camera 1 is a SIMPLE_RADIAL_FISHEYE camera",
            "supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV",
            "colmap image_undistorter",
        ],
    ),
    ("camera_rational", _rational_camera, ["camera 1 is a FULL_OPENCV camera with k4, k5, k6 not zero"]),
    ("image_missing", lambda w: (w["images"] / "s1_v2.png").unlink(), ["image 's1_v2.png' of the model is missing"]),
    ("images_dir_missing", lambda w: shutil.rmtree(w["images"]), ["image folder not found"]),
    ("image_wrong_size", _small_image, ["s0_v1.png: image is 32x32, its COLMAP camera 64x48"]),
    (
        "anchors_bad_row",
        lambda w: _replace(w["anchors"], "image,x,y,theta\ns0_v0.png,1,1,0\ns1_v0.png,abc,3,0.5\ns2_v0.png,4,1,1.5\n"),
        ["anchors.csv, line 3", "x 'abc' is not a number"],
    ),
    (
        "anchors_unknown_image",
        lambda w: _replace(w["anchors"], "image,x,y,theta\ns0_v0.png,1,1,0\nnope.png,2,3,0.5\ns2_v0.png,4,1,1.5\n"),
        ["line 3", "'nope.png' is not in the COLMAP model"],
    ),
    (
        "anchors_too_few",
        lambda w: _replace(w["anchors"], "image,x,y,theta\ns0_v0.png,1,1,0\ns1_v0.png,2,3,0.5\n"),
        ["2 usable anchors, the alignment needs at least 3"],
    ),
    (
        "anchors_collinear",
        lambda w: _replace(
            w["anchors"], "image,x,y,theta\ns0_v0.png,1,1,0\ns0_v1.png,1,1,1.047198\ns1_v0.png,2,3,0.5\n"
        ),
        ["anchors lie on one line"],
    ),
    ("anchors_missing", lambda w: w["anchors"].unlink(), ["anchors file is missing"]),
    ("anchors_mirrored", _mirrored_anchors, ["turns 24 of 24 cameras upside down", "anchors look mirrored"]),
    ("no_anchors", lambda w: w.update(anchors=None), ["no anchors given", "--in-map-frame"]),
    ("map_missing", lambda w: w["map"].unlink(), ["map.yaml", "file is missing"]),
    ("bad_name", lambda w: w.update(name="my site!"), ["--name", "key 'name'"]),
]


@pytest.fixture
def work(site, model_dir, tmp_path) -> dict:
    """Copies of every input, to break one at a time."""
    shutil.copytree(model_dir, tmp_path / "model")
    shutil.copytree(site / "images", tmp_path / "images")
    for f in ("map.yaml", "map.pgm"):
        shutil.copy(site / f, tmp_path / f)
    anchors = write_anchors(tmp_path / "anchors.csv", site, ANCHORS)
    return {
        "site": site,
        "model": tmp_path / "model",
        "images": tmp_path / "images",
        "map": tmp_path / "map.yaml",
        "anchors": anchors,
        "name": None,
        "out": tmp_path / "out",
    }


def run(w: dict) -> Path:
    inputs = {k: w[k] for k in ("model", "images", "map", "anchors")}
    return run_ingest_colmap(CFG, inputs=inputs, outputs={"out": w["out"]}, progress=False, name=w["name"])


def assert_no_output(out: Path) -> None:
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}.tmp-*"))


@pytest.mark.parametrize(("name", "breakage", "expected"), BREAKAGES, ids=[b[0] for b in BREAKAGES])
def test_bad_input_is_refused_with_a_clear_message_and_no_output(work, name, breakage, expected):
    breakage(work)
    with pytest.raises(InputError) as err:
        run(work)
    for text in expected:
        assert text in str(err.value), str(err.value)
    assert_no_output(work["out"])


def test_every_problem_is_listed_at_once(work):
    work["map"].unlink()
    _replace(work["anchors"], "image,x,y,theta\nnope.png,1,1,0\n")
    with pytest.raises(InputError) as err:
        run(work)
    text = str(err.value)
    assert "map.yaml" in text and "'nope.png' is not in the COLMAP model" in text and "0 usable anchors" in text
    assert_no_output(work["out"])


def test_an_existing_output_is_replaced_only_with_force(work):
    run(work)
    with pytest.raises(OutputExistsError):
        run(work)
    (work["out"] / "stale.txt").write_text("old")
    run_ingest_colmap(
        CFG,
        inputs={k: work[k] for k in ("model", "images", "map", "anchors")},
        outputs={"out": work["out"]},
        progress=False,
        force=True,
    )
    assert not (work["out"] / "stale.txt").exists() and (work["out"] / "captures.csv").is_file()


def test_cli_reports_bad_input_without_a_traceback(work):
    app = typer.Typer()
    app.command()(ingest_colmap)
    args = [str(work["model"]), "--images", str(work["images"]), "--map", str(work["map"]), "--out", str(work["out"])]
    work["map"].unlink()
    result = CliRunner().invoke(app, args + ["--anchors", str(work["anchors"])])
    assert result.exit_code == 1
    assert "Traceback" not in result.output and "error:" in result.output and "file is missing" in result.output
    assert_no_output(work["out"])
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1 and "Traceback" not in result.output and "no anchors given" in result.output


def test_cli_prints_the_alignment(work, site):
    app = typer.Typer()
    app.command()(ingest_colmap)
    args = [
        str(work["model"]),
        "--images",
        str(work["images"]),
        "--map",
        str(site / "map.yaml"),
        "--out",
        str(work["out"]),
        "--anchors",
        str(work["anchors"]),
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "alignment: sim3 fitted on anchor camera centres, scale 1" in result.output
    assert "3 anchors: position RMS 0.0000 m, max 0.0000 m" in result.output
    assert "  s1_v3.png: 0.0000 m, 0.000 deg" in result.output
    assert (
        f"wrote site 'out': 24 images in 4 stops (grouped by rig frames), 0 stops left out -> {work['out']}"
        in result.output
    )


def test_export_cli(site, tmp_path):
    app = typer.Typer()
    app.command()(export_colmap)
    result = CliRunner().invoke(app, [str(site), "--out", str(tmp_path / "model")])
    assert result.exit_code == 0, result.output
    assert "exported 'tiny': 24 images in 4 frames of a 6-camera rig, cameras at 1.2 m" in result.output
    assert f"image names are relative to {site / 'images'}" in result.output
    result = CliRunner().invoke(app, [str(tmp_path / "nowhere"), "--out", str(tmp_path / "m2")])
    assert result.exit_code == 1 and "Traceback" not in result.output and "site directory not found" in result.output


def test_commands_import_nothing_heavy():
    code = "import sys, stages.colmap; print([m for m in ('pycolmap', 'numpy') if m in sys.modules])"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert out.stdout.strip() == "[]"
