"""`ingest`: a valid site goes through; each kind of bad input is refused with a precise message and no output."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from PIL import Image

from pipeline.config import load_config
from pipeline.errors import InputError
from pipeline.ingest import run_ingest
from pipeline.io import tables
from pipeline.io.map_yaml import read_map
from tests.fixtures.capture_site import STOPS, write_capture_site


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_capture_site(tmp_path_factory.mktemp("pristine") / "site")


@pytest.fixture
def site(pristine, tmp_path) -> Path:
    dst = tmp_path / "site"
    shutil.copytree(pristine, dst)
    return dst


def ingest(site: Path, out: Path, **overrides):
    cfg = load_config("ci", [f"{k}={v}" for k, v in overrides.items()])
    return run_ingest(cfg, inputs={"site": site}, outputs={"out": out}, progress=False)


def edit_csv(path: Path, fn) -> None:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows = fn(rows)
    with path.open("w", newline="") as fh:
        fields = list(rows[0]) if rows else ["image"]
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


def edit_yaml(path: Path, fn) -> None:
    doc = yaml.safe_load(path.read_text())
    fn(doc)
    path.write_text(yaml.safe_dump(doc))


def edit_json(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def set_row(i: int, **values):
    def fn(rows):
        rows[i].update({k: str(v) for k, v in values.items()})
        return rows

    return fn


def set_stop(stop: str, **values):
    def fn(rows):
        for r in rows:
            if r["stop_id"] == stop:
                r.update({k: str(v) for k, v in values.items()})
        return rows

    return fn


def _bad_pickle(run: Path) -> None:
    np.save(run / "scans.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)


# (name, how to break the site, substrings the error must contain)
BREAKAGES = [
    ("site_yaml_missing", lambda s: (s / "site.yaml").unlink(), ["site.yaml", "file is missing"]),
    (
        "site_unknown_key",
        lambda s: edit_yaml(s / "site.yaml", lambda d: d["camera"].update(focal=3)),
        ["site.yaml", "camera.focal", "unknown key"],
    ),
    (
        "site_bad_value",
        lambda s: edit_yaml(s / "site.yaml", lambda d: d["camera"].update(width=-5)),
        ["site.yaml", "camera.width", "greater than 0"],
    ),
    ("map_image_missing", lambda s: (s / "map.pgm").unlink(), ["map.yaml", "key 'image'", "does not exist"]),
    (
        "map_bad_resolution",
        lambda s: edit_yaml(s / "map.yaml", lambda d: d.update(resolution=0)),
        ["map.yaml", "key 'resolution'", "positive"],
    ),
    (
        "map_thresholds_swapped",
        lambda s: edit_yaml(s / "map.yaml", lambda d: d.update(free_thresh=0.9)),
        ["map.yaml", "key 'free_thresh'", "below occupied_thresh"],
    ),
    ("map_image_corrupt", lambda s: (s / "map.pgm").write_bytes(b"P5 garbage"), ["map.pgm", "unreadable map image"]),
    (
        "captures_missing_column",
        lambda s: edit_csv(
            s / "captures.csv", lambda rows: [{k: v for k, v in r.items() if k != "theta"} for r in rows]
        ),
        ["captures.csv", "line 1", "['theta']"],
    ),
    (
        "captures_not_a_number",
        lambda s: edit_csv(s / "captures.csv", set_row(1, x="abc")),
        ["captures.csv, line 3", "x 'abc' is not a number"],
    ),
    ("pose_nan", lambda s: edit_csv(s / "captures.csv", set_row(2, y="nan")), ["line 4", "y is nan"]),
    (
        "duplicate_image",
        lambda s: edit_csv(s / "captures.csv", lambda rows: rows + [rows[0]]),
        ["line 26", "duplicate image id 'images/s0_v0.png' (first on line 2)"],
    ),
    (
        "image_missing",
        lambda s: (s / "images" / "s1_v2.png").unlink(),
        ["line 10", "'images/s1_v2.png' does not exist"],
    ),
    (
        "image_unreadable",
        lambda s: (s / "images" / "s1_v3.png").write_bytes(b"\x89PNG\r\n broken"),
        ["line 11", "'images/s1_v3.png' is unreadable"],
    ),
    (
        "image_wrong_size",
        lambda s: Image.new("RGB", (32, 32)).save(s / "images" / "s2_v0.png"),
        ["line 14", "is 32x32", "64x48"],
    ),
    (
        "image_path_escapes",
        lambda s: edit_csv(s / "captures.csv", set_row(0, image="../outside.png")),
        ["line 2", "leaves the site directory"],
    ),
    (
        "pose_outside_map",
        lambda s: edit_csv(s / "captures.csv", set_stop("s3", x=50.0)),
        ["(50.00, 3.00)", "outside the map"],
    ),
    ("pose_in_wall", lambda s: edit_csv(s / "captures.csv", set_stop("s2", x=3.0, y=0.5)), ["inside a wall"]),
    (
        "stop_view_missing",
        lambda s: edit_csv(s / "captures.csv", lambda rows: rows[:-1]),
        ["stop 's3' has 5 views, the rig has 6"],
    ),
    ("stop_view_repeated", lambda s: edit_csv(s / "captures.csv", set_row(7, view=0)), ["stop 's1' repeats views [0]"]),
    ("stop_view_out_of_range", lambda s: edit_csv(s / "captures.csv", set_row(5, view=9)), ["outside 0..5"]),
    (
        "stop_heading_mismatch",
        lambda s: edit_csv(s / "captures.csv", set_row(3, theta=0.0)),
        ["stop 's0'", "disagree with the rig yaw offsets"],
    ),
    ("stop_views_apart", lambda s: edit_csv(s / "captures.csv", set_row(4, x=1.5)), ["stop 's0' are 0.417 m apart"]),
    (
        "box_outside_image",
        lambda s: edit_json(s / "annotations.json", lambda d: d["annotations"][5].update(bbox=[60, 10, 16, 20])),
        ["annotations.json", "annotations[5] (id 6)", "leaves the 64x48 image"],
    ),
    (
        "box_unknown_class",
        lambda s: edit_json(s / "annotations.json", lambda d: d["categories"][0].update(name="sofa")),
        ["category 'sofa'", "not a class of site.yaml"],
    ),
    (
        "box_unknown_category_id",
        lambda s: edit_json(s / "annotations.json", lambda d: d["annotations"][0].update(category_id=99)),
        ["annotations[0] (id 1) has unknown category_id 99"],
    ),
    (
        "box_degenerate",
        lambda s: edit_json(s / "annotations.json", lambda d: d["annotations"][2].update(bbox=[5, 5, 0, 10])),
        ["annotations[2]", "smaller than"],
    ),
    (
        "box_image_not_captured",
        lambda s: edit_json(s / "annotations.json", lambda d: d["images"][0].update(file_name="images/other.png")),
        ["images[0] file_name 'images/other.png' is not in captures.csv"],
    ),
    (
        "annotations_not_json",
        lambda s: (s / "annotations.json").write_text("{not json"),
        ["annotations.json", "not valid JSON"],
    ),
    (
        "run_scan_count",
        lambda s: np.save(s / "runs/query_a/scans.npy", np.load(s / "runs/query_a/scans.npy")[:-1]),
        ["scans.npy", "has 8 scans but trajectory.csv has 9"],
    ),
    (
        "run_beam_count",
        lambda s: np.save(s / "runs/query_a/scans.npy", np.load(s / "runs/query_a/scans.npy")[:, :50]),
        ["has 50 beams per scan", "laser.beams is 91"],
    ),
    ("run_pickled_scans", lambda s: _bad_pickle(s / "runs/query_a"), ["scans.npy", "without pickle"]),
    (
        "run_time_backwards",
        lambda s: edit_csv(s / "runs/query_a/trajectory.csv", set_row(4, t=0.1)),
        ["trajectory.csv, line 6", "does not increase"],
    ),
    (
        "run_partial_ground_truth",
        lambda s: edit_csv(s / "runs/query_a/trajectory.csv", set_row(2, gt_y="")),
        ["trajectory.csv, line 4", "all given or all empty"],
    ),
    (
        "run_gt_in_wall",
        lambda s: edit_csv(s / "runs/query_a/trajectory.csv", set_row(1, gt_x=3.0, gt_y=0.5)),
        ["trajectory.csv, line 3", "inside a wall"],
    ),
]


def test_valid_site_is_ingested(site, tmp_path):
    out = ingest(site, tmp_path / "out")
    images = tables.read_table(out / "images.parquet", "images")
    assert images.num_rows == 6 * len(STOPS)
    assert set(images.column("split").to_pylist()) == {"train", "test"}
    # whole stops: every stop has one split
    by_stop = {}
    for stop, split in zip(images.column("stop_id").to_pylist(), images.column("split").to_pylist(), strict=True):
        by_stop.setdefault(stop, set()).add(split)
    assert all(len(v) == 1 for v in by_stop.values())
    import hashlib

    first = images.slice(0, 1).to_pylist()[0]
    assert first["sha256"] == hashlib.sha256((site / first["image_id"]).read_bytes()).hexdigest()
    assert (out / first["image_id"]).is_file()
    boxes = tables.read_table(out / "boxes.parquet", "boxes")
    assert boxes.num_rows == 24
    assert set(boxes.column("class_id").to_pylist()) == {1, 2, 3}
    run = tables.read_table(out / "runs" / "query_a.parquet", "runs")
    assert run.num_rows == 9 and len(run.column("ranges")[0]) == 91
    assert np.allclose(run.column("angle_min").to_numpy(), np.radians(-135))
    assert np.array_equal(read_map(out / "map.yaml").grid, read_map(site / "map.yaml").grid)
    assert yaml.safe_load((out / "config.yaml").read_text())["stage"] == "ingest"
    assert json.loads((out / "report.json").read_text())["stops"] == len(STOPS)


def test_ingest_is_deterministic(site, tmp_path):
    a, b = ingest(site, tmp_path / "a"), ingest(site, tmp_path / "b")
    for name in ("images.parquet", "boxes.parquet", "runs/query_a.parquet", "map.pgm", "report.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert pq.read_table(a / "images.parquet").equals(pq.read_table(b / "images.parquet"))


def test_split_seed_changes_split(site, tmp_path):
    s0 = tables.read_table(
        ingest(site, tmp_path / "a", **{"ingest.split.test_fraction": 0.5}) / "images.parquet", "images"
    )
    splits = {
        seed: tables.read_table(
            ingest(site, tmp_path / f"s{seed}", **{"ingest.split.test_fraction": 0.5, "ingest.split.seed": seed})
            / "images.parquet",
            "images",
        )
        .column("split")
        .to_pylist()
        for seed in range(1, 6)
    }
    assert any(v != s0.column("split").to_pylist() for v in splits.values())
    assert all(v.count("test") == 12 for v in splits.values())


@pytest.mark.parametrize(("name", "breaker", "expected"), BREAKAGES, ids=[b[0] for b in BREAKAGES])
def test_bad_input_is_refused(site, tmp_path, name, breaker, expected):
    breaker(site)
    out = tmp_path / "out"
    with pytest.raises(InputError) as exc:
        ingest(site, out)
    text = str(exc.value)
    for fragment in expected:
        assert fragment in text, f"{name}: {fragment!r} not in:\n{text}"
    assert not out.exists()
    assert not list(tmp_path.glob(".out.tmp-*"))


def test_all_problems_are_listed_at_once(site, tmp_path):
    (site / "images" / "s1_v2.png").unlink()
    edit_csv(site / "captures.csv", set_row(2, y="nan"))
    edit_json(site / "annotations.json", lambda d: d["categories"][0].update(name="sofa"))
    with pytest.raises(InputError) as exc:
        ingest(site, tmp_path / "out")
    assert len(exc.value.problems) >= 3
    text = str(exc.value)
    assert "does not exist" in text and "y is nan" in text and "sofa" in text


def test_existing_output_needs_force(site, tmp_path):
    from pipeline.errors import OutputExistsError

    out = ingest(site, tmp_path / "out")
    marker = out / "images.parquet"
    before = marker.read_bytes()
    with pytest.raises(OutputExistsError):
        ingest(site, out)
    cfg = load_config("ci")
    run_ingest(cfg, inputs={"site": site}, outputs={"out": out}, force=True, progress=False)
    assert marker.read_bytes() == before


def test_documented_example_site_is_valid(tmp_path):
    example = Path(__file__).resolve().parents[1] / "docs" / "example-site"
    out = ingest(example, tmp_path / "out")
    assert tables.read_table(out / "images.parquet", "images").num_rows == 24


def test_documented_site_yaml_snippet_is_valid():
    import re

    from pipeline.io.site import Site

    doc = (Path(__file__).resolve().parents[1] / "docs" / "capture-format.md").read_text()
    snippet = re.search(r"## `site.yaml`\n```yaml\n(.*?)```", doc, re.S).group(1)
    site = Site.model_validate(yaml.safe_load(snippet))
    assert site.laser.beams == 91 and len(site.rig.yaw_offsets) == 6
