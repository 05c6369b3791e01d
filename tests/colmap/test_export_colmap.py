"""`export-colmap`: the site's views reopen in pycolmap with their poses, a rig of 6 cameras and one frame per stop."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from pipeline.colmap.align import map_pose
from pipeline.colmap.export import run_export_colmap
from pipeline.errors import InputError, OutputExistsError
from pipeline.ingest import run_ingest
from tests.colmap import CFG, angle_diff, read_rows
from tests.fixtures.capture_site import OFFSETS_DEG, STOPS, write_capture_site


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    return write_capture_site(tmp_path_factory.mktemp("export") / "site", with_run=False)


def export(site: Path, out: Path, **kw) -> pycolmap.Reconstruction:
    run_export_colmap(CFG, inputs={"site": site}, outputs={"out": out}, **kw)
    return pycolmap.Reconstruction(str(out))


def check_poses(rec: pycolmap.Reconstruction, site: Path, height: float) -> None:
    rows = read_rows(site / "captures.csv")
    assert rec.num_images() == len(rows) == 24 and rec.num_reg_images() == 24
    for image in rec.images.values():
        r = rows[f"images/{image.name}"]
        centre, heading = map_pose(image.cam_from_world(), pycolmap.Sim3d())
        np.testing.assert_allclose(centre, [r["x"], r["y"], height], atol=1e-9)
        assert angle_diff(heading, r["theta"]) < 1e-6  # captures.csv rounds theta to 1e-6 rad
        np.testing.assert_allclose(image.projection_center(), centre, atol=1e-12)
        axis = np.asarray(image.cam_from_world().rotation.matrix()).T @ [0.0, 0.0, 1.0]
        assert abs(axis[2]) < 1e-12  # the optical axis is horizontal


def test_export_reopens_with_the_same_poses(site, tmp_path):
    rec = export(site, tmp_path / "model")
    assert sorted(p.name for p in (tmp_path / "model").iterdir()) == [
        "cameras.bin",
        "config.yaml",
        "frames.bin",
        "images.bin",
        "points3D.bin",
        "rigs.bin",
    ]
    check_poses(rec, site, 1.2)
    assert rec.num_points3D() == 0
    # One camera per view with the site's intrinsics (principal point + 0.5: COLMAP's pixel centres).
    assert sorted(rec.cameras) == [1, 2, 3, 4, 5, 6]
    for cam in rec.cameras.values():
        assert cam.model_name == "PINHOLE" and (cam.width, cam.height) == (64, 48)
        np.testing.assert_allclose(cam.params, [40.0, 40.0, 32.5, 24.5])
    # One rig: camera 1 (view 0) is the reference, camera k + 1 turned by the rig's yaw offset k.
    assert rec.num_rigs() == 1
    rig = rec.rig(1)
    assert rig.ref_sensor_id.id == 1 and rig.num_sensors() == 6
    for sensor, cam_from_rig in rig.non_ref_sensors.items():
        yaw = math.radians(OFFSETS_DEG[sensor.id - 1])
        assert math.degrees(cam_from_rig.rotation.angle()) == pytest.approx(
            abs(math.degrees(math.remainder(yaw, 2 * math.pi))), abs=1e-9
        )
        np.testing.assert_allclose(cam_from_rig.translation, 0.0, atol=1e-12)
    # One frame per stop holding its six views, each on the camera of its view.
    assert rec.num_frames() == len(STOPS)
    for frame in rec.frames.values():
        names = sorted(rec.image(d.id).name for d in frame.data_ids)
        stop = names[0].split("_")[0]
        assert names == [f"{stop}_v{v}.png" for v in range(6)]
        for d in frame.data_ids:
            assert d.sensor_id.id == int(rec.image(d.id).name[-5]) + 1 == rec.image(d.id).camera_id


def test_export_text_format_and_camera_height(site, tmp_path):
    rec = export(site, tmp_path / "model", camera_height=0.8, text=True)
    assert {"cameras.txt", "images.txt", "points3D.txt", "rigs.txt", "frames.txt"} <= {
        p.name for p in (tmp_path / "model").iterdir()
    }
    check_poses(rec, site, 0.8)


def test_export_of_an_ingest_output_equals_that_of_the_capture_directory(site, tmp_path):
    ingested = run_ingest(CFG, inputs={"site": site}, outputs={"out": tmp_path / "ing"}, progress=False)
    a = export(site, tmp_path / "a")
    b = export(ingested, tmp_path / "b")
    for image in a.images.values():
        other = b.find_image_with_name(image.name)
        np.testing.assert_allclose(other.cam_from_world().matrix(), image.cam_from_world().matrix(), atol=1e-12)


def test_export_refuses_bad_input_and_existing_output(site, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(site, broken)
    lines = (broken / "captures.csv").read_text().splitlines()
    (broken / "captures.csv").write_text("\n".join(lines[:-1]) + "\n")  # stop s3 loses a view
    with pytest.raises(InputError) as err:
        export(broken, tmp_path / "model")
    assert "stop 's3' has 5 views, the rig has 6" in str(err.value)
    with pytest.raises(InputError) as err:
        export(tmp_path / "nowhere", tmp_path / "model")
    assert "site directory not found" in str(err.value)
    with pytest.raises(InputError) as err:
        export(site, tmp_path / "model", camera_height=float("nan"))
    assert "--camera-height" in str(err.value)
    assert not (tmp_path / "model").exists()
    export(site, tmp_path / "model")
    with pytest.raises(OutputExistsError):
        export(site, tmp_path / "model")
    export(site, tmp_path / "model", force=True, camera_height=2.0)
    check_poses(pycolmap.Reconstruction(str(tmp_path / "model")), site, 2.0)
