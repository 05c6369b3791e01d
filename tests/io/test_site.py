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
