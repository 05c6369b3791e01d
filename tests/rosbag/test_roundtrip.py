"""export-bag -> ingest-bag -> ingest gives back the capture directory it started from, in each format."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.io import tables
from pipeline.io.map_yaml import read_map
from pipeline.io.site import read_site
from pipeline.rosbag.export import run_export_bag
from pipeline.rosbag.ingest import run_ingest_bag
from tests.fixtures.capture_site import write_capture_site


def _ingested(cfg, site, out):
    from pipeline.ingest import run_ingest

    return run_ingest(cfg, inputs={"site": site}, outputs={"out": out}, progress=False)


def _stops(ingested) -> list[dict]:
    """Stops in capture order (by their first image's row), each {view: (x, y, theta, sha256)}."""
    t = tables.read_table(ingested / "images.parquet", "images").to_pydict()
    stops: dict[str, dict] = {}
    for i in range(len(t["image_id"])):
        stops.setdefault(t["stop_id"][i], {})[t["view"][i]] = (t["x"][i], t["y"][i], t["theta"][i], t["sha256"][i])
    return list(stops.values())


def assert_same_site(direct, via_bag, *, views_exact: bool = True):
    a, b = _stops(direct), _stops(via_bag)
    assert len(a) == len(b)
    for sa, sb in zip(a, b, strict=True):
        assert sorted(sa) == sorted(sb)
        for view in sa:
            (xa, ya, ta, ha), (xb, yb, tb, hb) = sa[view], sb[view]
            assert np.hypot(xa - xb, ya - yb) <= 0.01
            assert abs(np.degrees(np.angle(np.exp(1j * (ta - tb))))) <= 0.5
            if views_exact:
                assert ha == hb  # the very frame, byte for byte
    sa, sb = read_site(direct / "site.yaml"), read_site(via_bag / "site.yaml")
    assert sa.camera == sb.camera
    assert sa.laser.beams == sb.laser.beams
    assert sa.laser.angle_min_deg == pytest.approx(sb.laser.angle_min_deg, abs=1e-4)
    ma, mb = read_map(direct / "map.yaml"), read_map(via_bag / "map.yaml")
    assert np.array_equal(ma.grid, mb.grid) and ma.resolution == mb.resolution
    assert (ma.origin_x, ma.origin_y) == pytest.approx((mb.origin_x, mb.origin_y))
    runs_a = sorted(p.name for p in (direct / "runs").glob("*.parquet"))
    assert runs_a == sorted(p.name for p in (via_bag / "runs").glob("*.parquet"))
    for name in runs_a:
        ra = tables.read_table(direct / "runs" / name, "runs").to_pydict()
        rb = tables.read_table(via_bag / "runs" / name, "runs").to_pydict()
        for key in ("t", "odom_x", "odom_y", "odom_theta", "gt_x", "gt_y"):
            assert np.allclose(ra[key], rb[key], atol=1e-6), key
        assert np.allclose(np.array(ra["ranges"]), np.array(rb["ranges"]))
        assert [bool(k) for k in ra["kidnapped"]] == [bool(k) for k in rb["kidnapped"]]
        assert [i is None for i in ra["image_id"]] == [i is None for i in rb["image_id"]]


@pytest.mark.parametrize("fmt", ["mcap", "db3", "bag"])
def test_round_trip_each_format(tmp_path, fmt):
    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site")
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, fmt=fmt, progress=False)
    names = sorted(p.name for p in bags.iterdir() if p.name not in ("config.yaml", "export_report.json"))
    assert names == (["capture.bag", "query_a.bag"] if fmt == "bag" else ["capture", "query_a"])
    back = run_ingest_bag(cfg, inputs={"bags": [bags], "annotations": site / "annotations.json"},
                          outputs={"out": tmp_path / "back"}, progress=False)
    assert_same_site(_ingested(cfg, site, tmp_path / "a"), _ingested(cfg, back, tmp_path / "b"))


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_a_distorted_camera_round_trips_through_camera_info(tmp_path, fmt):
    from pipeline.io.site import Distortion, write_site
    from pipeline.rosbag.bagfile import open_reader
    from pipeline.rosbag.messages import field

    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site", with_run=False)
    plain = read_site(site / "site.yaml")
    coeffs = (-0.05, 0.01, 0.001, -0.002, 0.0005)
    camera = plain.camera.model_copy(update={"distortion": Distortion(coeffs=coeffs)})
    write_site(site / "site.yaml", plain.model_copy(update={"camera": camera}))
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, fmt=fmt, progress=False)
    with open_reader(bags / ("capture.bag" if fmt == "bag" else "capture")) as reader:
        info = next(reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                    if c.topic == "/camera/camera_info")
    assert info.distortion_model == "plumb_bob" and tuple(field(info, "d")) == coeffs
    back = run_ingest_bag(cfg, inputs={"bags": [bags]}, outputs={"out": tmp_path / "back"}, progress=False)
    assert read_site(back / "site.yaml").camera == camera


def test_round_trip_of_the_rendered_reference_site(micro_site, tmp_path):
    """The CI micro site that `siteloc synth` rendered, through mcap, with its kidnapped query runs."""
    cfg, ing, _ = micro_site
    site = ing.parent / "site"
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, progress=False)
    back = run_ingest_bag(cfg, inputs={"bags": [bags], "annotations": site / "annotations.json"},
                          outputs={"out": tmp_path / "back"}, progress=False)
    via_bag = _ingested(cfg, back, tmp_path / "b")
    assert_same_site(ing, via_bag)
    kid = [k for p in sorted((ing / "runs").glob("query_*.parquet"))
           for k in tables.read_table(p, "runs").to_pydict()["kidnapped"]]
    assert any(kid), "the micro site's query runs are kidnapped: the round trip must find those steps"


def test_export_is_reproducible(tmp_path):
    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site")
    a = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "a"}, fmt="bag", progress=False)
    b = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "b"}, fmt="bag", progress=False)
    for name in ("capture.bag", "query_a.bag"):
        assert (a / name).read_bytes() == (b / name).read_bytes()


def test_export_keeps_the_mounts_of_a_site_that_came_from_a_recording(tmp_path):
    """site.yaml's extrinsics (as ingest-bag writes them) go back into /tf_static unchanged."""
    import yaml
    from scipy.spatial.transform import Rotation

    from pipeline.io.site import Site
    from pipeline.rosbag.export import OPTICAL, camera_on_floor

    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site")
    doc = yaml.safe_load((site / "site.yaml").read_text())
    doc["laser"]["mount"] = {"x": 0.1, "y": 0.0, "yaw_deg": 0.0}
    optical = [float(v) for v in Rotation.from_matrix(OPTICAL).as_quat()]
    doc["extrinsics"] = {"base_from_camera": {"xyz": [0.0, 0.0, 1.55], "quat_xyzw": optical},
                         "base_from_laser": {"xyz": [0.1, 0.0, 0.25], "quat_xyzw": [0.0, 0.0, 0.0, 1.0]}}
    (site / "site.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, progress=False)
    back = run_ingest_bag(cfg, inputs={"bags": [bags]}, outputs={"out": tmp_path / "back"}, progress=False)
    ext = read_site(back / "site.yaml").extrinsics
    assert ext.base_from_camera.xyz == (0.0, 0.0, 1.55) and ext.base_from_laser.xyz == (0.1, 0.0, 0.25)
    assert read_site(back / "site.yaml").laser.mount.x == 0.1
    # a camera looking left from 0.2 m ahead of the base: the base stands behind and to the right of it
    left = Rotation.from_euler("z", 90, degrees=True) * Rotation.from_matrix(OPTICAL)
    doc["extrinsics"]["base_from_camera"] = {"xyz": [0.2, 0.0, 1.2], "quat_xyzw": [float(v) for v in left.as_quat()]}
    floor = camera_on_floor(Site.model_validate(doc), 1.2)[0]
    assert floor == pytest.approx([0.2, 0.0, np.pi / 2])


def test_only_the_kept_frames_are_read_into_memory(tmp_path):
    import csv

    from pipeline.rosbag.read import load_frames, read_recording

    cfg = load_config("demo")
    site = write_capture_site(tmp_path / "site")
    bags = run_export_bag(cfg, inputs={"site": site}, outputs={"out": tmp_path / "bags"}, fmt="bag", progress=False)
    rec = read_recording(bags / "capture.bag")
    assert len(rec.frames) == 24 and all(data is None for _, _, data, _ in rec.frames)
    load_frames(rec, {0, 7})
    views = [r["image"] for r in csv.DictReader((site / "captures.csv").open())]
    assert rec.frames[0][2] == (site / views[0]).read_bytes() and rec.frames[7][2] == (site / views[7]).read_bytes()
    assert sum(data is not None for _, _, data, _ in rec.frames) == 2
