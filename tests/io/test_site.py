"""site.yaml's optional extrinsics: read back as written, a non-unit quaternion named with its key."""

import pytest
import yaml

from pipeline.errors import InputError
from pipeline.io.site import read_site, write_site
from tests.fixtures.capture_site import site_yaml


def test_extrinsics_round_trip_and_are_left_out_when_absent(tmp_path):
    doc = site_yaml()
    write_site(tmp_path / "plain.yaml", read_site_from(tmp_path, doc))
    assert "extrinsics" not in yaml.safe_load((tmp_path / "plain.yaml").read_text())
    doc["extrinsics"] = {"base_from_camera": {"xyz": [0.0, 0.0, 1.2], "quat_xyzw": [0.5, -0.5, 0.5, -0.5]}}
    site = read_site_from(tmp_path, doc)
    write_site(tmp_path / "again.yaml", site)
    assert read_site(tmp_path / "again.yaml") == site
    assert site.extrinsics.base_from_laser is None and site.extrinsics.base_from_camera.xyz == (0.0, 0.0, 1.2)


def test_a_quaternion_that_is_not_unit_is_an_error(tmp_path):
    doc = site_yaml()
    doc["extrinsics"] = {"base_from_laser": {"xyz": [0.0, 0.0, 0.3], "quat_xyzw": [0.0, 0.0, 0.0, 0.0]}}
    with pytest.raises(InputError, match="extrinsics.base_from_laser") as err:
        read_site_from(tmp_path, doc)
    assert "unit quaternion" in str(err.value)


def read_site_from(tmp_path, doc):
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return read_site(tmp_path / "site.yaml")


def test_a_site_without_distortion_dumps_exactly_as_before(tmp_path):
    write_site(tmp_path / "site.yaml", read_site_from(tmp_path, site_yaml()))
    assert (tmp_path / "site.yaml").read_text().startswith(
        "name: tiny\ncamera:\n  width: 64\n  height: 48\n  fx: 40.0\n  fy: 40.0\n  cx: 32.0\n  cy: 24.0\nrig:\n")


def test_distortion_round_trips_in_opencv_order(tmp_path):
    doc = site_yaml()
    doc["camera"]["distortion"] = {"model": "plumb_bob", "coeffs": [-0.05, 0.01, 0.001, -0.002, 0.0]}
    site = read_site_from(tmp_path, doc)
    assert site.camera.distortion.coeffs == (-0.05, 0.01, 0.001, -0.002, 0.0)
    write_site(tmp_path / "again.yaml", site)
    assert yaml.safe_load((tmp_path / "again.yaml").read_text())["camera"]["distortion"] == doc["camera"]["distortion"]
    assert read_site(tmp_path / "again.yaml") == site
    doc["camera"]["distortion"] = {"coeffs": [0.1, 0.0, 0.0, 0.0, 0.0]}  # the model defaults to plumb_bob
    assert read_site_from(tmp_path, doc).camera.distortion.model == "plumb_bob"


@pytest.mark.parametrize(
    ("distortion", "key", "text"),
    [
        ({"model": "equidistant", "coeffs": [0.1, 0.0, 0.0, 0.0, 0.0]}, "camera.distortion.model", "'plumb_bob'"),
        ({"model": "plumb_bob", "coeffs": [0.1, 0.0, 0.0, 0.0]}, "camera.distortion.coeffs", "at least 5 items"),
        ({"coeffs": [0.1, 0.0, 0.0, 0.0, float("nan")]}, "camera.distortion.coeffs.4", "finite number"),
        ({"coeffs": [0.1, 0.0, 0.0, 0.0, 0.0], "k1": 0.1}, "camera.distortion.k1", "unknown key"),
    ],
)
def test_a_bad_distortion_is_an_error_naming_its_key(tmp_path, distortion, key, text):
    doc = site_yaml()
    doc["camera"]["distortion"] = distortion
    with pytest.raises(InputError, match=key.replace(".", r"\.")) as err:
        read_site_from(tmp_path, doc)
    assert text in str(err.value)


def test_the_documented_distortion_example_is_valid():
    from pathlib import Path

    from pipeline.io.site import Camera

    doc = (Path(__file__).resolve().parents[2] / "docs" / "capture-format.md").read_text()
    snippet = next(b for b in doc.split("```yaml\n")[1:] if "distortion:" in b.split("```")[0]).split("```")[0]
    camera = Camera.model_validate(yaml.safe_load(snippet)["camera"])
    assert camera.distortion.coeffs == (-0.05, 0.01, 0.0, 0.0, 0.0)
