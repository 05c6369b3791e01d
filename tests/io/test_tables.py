"""Parquet tables: round trips of every table, schema versions, refusal of the wrong table."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.errors import InputError
from pipeline.io import tables


def sample(kind: str) -> dict:
    if kind == "images":
        return {
            "image_id": ["images/a.jpg", "images/b.jpg"],
            "stop_id": ["s0", "s0"],
            "view": [0, 1],
            "x": [1.0, 1.0],
            "y": [2.0, 2.0],
            "theta": [0.0, 1.047],
            "room": ["r1", None],
            "area": ["a", None],
            "split": ["train", "train"],
            "width": [640, 640],
            "height": [480, 480],
            "sha256": ["0" * 64, "1" * 64],
        }
    if kind == "boxes":
        return {
            "image_id": ["images/a.jpg"],
            "class_id": [3],
            "class_name": ["chair"],
            "x1": [1.5],
            "y1": [2.0],
            "x2": [10.0],
            "y2": [20.25],
        }
    return {
        "run": ["r", "r"],
        "step": [0, 1],
        "t": [0.0, 0.1],
        "odom_x": [0.0, 0.1],
        "odom_y": [0.0, 0.0],
        "odom_theta": [0.0, 0.01],
        "gt_x": [1.0, None],
        "gt_y": [2.0, None],
        "gt_theta": [0.5, None],
        "ranges": [np.array([1.0, 2.5, 30.0], dtype=np.float32), np.array([1.1, 2.4, 29.0], dtype=np.float32)],
        "angle_min": [-2.35, -2.35],
        "angle_increment": [0.1, 0.1],
        "range_max": [30.0, 30.0],
        "image_id": ["images/a.jpg", None],
        "kidnapped": [False, None],
    }


@pytest.mark.parametrize("kind", ["images", "boxes", "runs"])
def test_round_trip(tmp_path, kind):
    table = tables.to_table(kind, sample(kind), metadata={"site": "x"})
    tables.write_table(tmp_path / "t.parquet", table, kind)
    back = tables.read_table(tmp_path / "t.parquet", kind)
    assert back.to_pylist() == table.to_pylist()
    assert back.schema.remove_metadata() == tables.SCHEMAS[kind].remove_metadata()
    meta = tables.table_metadata(back)
    assert meta["table"] == kind and meta["schema_version"] == tables.SCHEMA_VERSION and meta["site"] == "x"


def test_float_columns_are_exact_float32(tmp_path):
    table = tables.to_table("runs", sample("runs"))
    tables.write_table(tmp_path / "r.parquet", table, "runs")
    ranges = tables.read_table(tmp_path / "r.parquet", "runs").column("ranges").to_pylist()
    assert np.array_equal(np.array(ranges[0], dtype=np.float32), sample("runs")["ranges"][0])


def test_wrong_kind_is_refused(tmp_path):
    tables.write_table(tmp_path / "b.parquet", tables.to_table("boxes", sample("boxes")), "boxes")
    with pytest.raises(InputError, match="holds a 'boxes' table, expected 'images'"):
        tables.read_table(tmp_path / "b.parquet", "images")


def test_unknown_major_version_is_refused(tmp_path):
    table = tables.to_table("boxes", sample("boxes"))
    meta = dict(table.schema.metadata)
    meta[b"siteloc.schema_version"] = b"2.0"
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "b.parquet")
    with pytest.raises(InputError, match="schema version '2.0'"):
        tables.read_table(tmp_path / "b.parquet", "boxes")


def test_foreign_parquet_is_refused(tmp_path):
    pq.write_table(pa.table({"a": [1]}), tmp_path / "f.parquet")
    with pytest.raises(InputError) as exc:
        tables.read_table(tmp_path / "f.parquet", "runs")
    assert "expected 'runs'" in str(exc.value) and "missing columns" in str(exc.value)


def test_not_parquet_and_missing(tmp_path):
    (tmp_path / "x.parquet").write_text("hello")
    with pytest.raises(InputError, match="not a readable Parquet file"):
        tables.read_table(tmp_path / "x.parquet", "runs")
    with pytest.raises(InputError, match="not found"):
        tables.read_table(tmp_path / "missing.parquet", "runs")


def test_interrupted_write_leaves_nothing(tmp_path):
    table = tables.to_table("boxes", sample("boxes"))
    bad = table.set_column(0, "image_id", pa.array([None], type=pa.string()))
    with pytest.raises(ValueError, match="non-nullable"):
        tables.write_table(tmp_path / "b.parquet", bad, "boxes")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".parquet", ".arrow"])
def test_parts_write_the_table_of_their_concatenation(tmp_path, suffix):
    rng = np.random.default_rng(0)
    parts = []
    for k, n in enumerate((3, 0, 5)):
        desc = rng.standard_normal((n, 4)).astype(np.float32)
        parts.append(tables.to_table("ipa", {"image_id": [f"i{k}-{j}" for j in range(n)],
                                              "descriptor": tables.descriptor_array(desc)}, metadata={"model": "m"}))
    whole, streamed = tmp_path / f"whole{suffix}", tmp_path / f"parts{suffix}"
    tables.write_table(whole, pa.concat_tables(parts), "ipa", {"dim": "4"})
    assert tables.write_table_parts(streamed, iter(parts), "ipa", {"dim": "4"}) == 8
    a, b = tables.read_table(whole, "ipa"), tables.read_table(streamed, "ipa")
    assert a.equals(b, check_metadata=True)
    assert tables.table_metadata(b)["model"] == "m" and tables.table_metadata(b)["dim"] == "4"
    with pytest.raises(ValueError, match="no parts"):
        tables.write_table_parts(tmp_path / f"none{suffix}", iter(()), "ipa")
    assert not (tmp_path / f"none{suffix}").exists()
