"""Descriptor tables: fixed_size_list<float32> round trip, and files that break the contract are refused."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.errors import InputError
from pipeline.io import tables


def test_ipa_round_trip_keeps_the_fixed_size_and_the_values(tmp_path):
    m = np.random.default_rng(0).normal(size=(6, 9)).astype(np.float32)
    t = tables.to_table("ipa", {"image_id": [f"im{i}" for i in range(6)], "descriptor": tables.descriptor_array(m)})
    tables.write_table(tmp_path / "ipa.parquet", t, "ipa", {"dim": "9"})
    back = tables.read_table(tmp_path / "ipa.parquet", "ipa")
    assert back.schema.field("descriptor").type == pa.list_(pa.float32(), 9)
    assert tables.table_metadata(back)["dim"] == "9"
    np.testing.assert_array_equal(tables.descriptor_matrix(back), m)


def test_a_variable_length_descriptor_column_is_refused(tmp_path):
    t = pa.table({"image_id": ["a"], "descriptor": pa.array([[1.0, 2.0]], type=pa.list_(pa.float32()))})
    t = t.replace_schema_metadata({b"siteloc.table": b"ipa", b"siteloc.schema_version": b"1.0"})
    pq.write_table(t, tmp_path / "ipa.parquet")
    with pytest.raises(InputError) as err:
        tables.read_table(tmp_path / "ipa.parquet", "ipa")
    assert "fixed_size_list" in str(err.value.problems[0])


def test_an_rpa_table_is_not_read_as_ipa(tmp_path):
    m = np.ones((1, 4), np.float32)
    cols = {"image_id": ["a"], "region": [0], "source": ["proposal"], "x1": [0.0], "y1": [0.0], "x2": [1.0],
            "y2": [1.0], "score": [0.5], "class_id": [0], "descriptor": tables.descriptor_array(m)}
    tables.write_table(tmp_path / "rpa.parquet", tables.to_table("rpa", cols), "rpa")
    with pytest.raises(InputError, match="not a valid ipa table"):
        tables.read_table(tmp_path / "rpa.parquet", "ipa")
