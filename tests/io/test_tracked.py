"""headline.json and plots/<name>.csv (what DVC compares): round trips, null for NaN, atomic writes."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from pipeline.io.tracked import headline_doc, plot_table_text, write_headline, write_plot_table


def test_headline_round_trips_with_nan_as_null_and_six_digits(tmp_path):
    figures = {"loss_first": 2.718281828459045, "val_loss": float("nan"), "steps": np.int64(12),
               "map": np.float32(0.25), "missing": None, "flag": True,
               "ipa": {"map_at_4": 0.1234567891, "recall_at_1": float("inf")}}
    path = write_headline(tmp_path, figures)
    assert path == tmp_path / "headline.json"
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text and text.endswith("\n")
    back = json.loads(text)
    assert back == {"loss_first": 2.71828, "val_loss": None, "steps": 12, "map": 0.25, "missing": None,
                    "flag": 1, "ipa": {"map_at_4": 0.123457, "recall_at_1": None}}
    assert list(back) == list(figures)  # the caller's order, for a readable `dvc metrics show`
    assert isinstance(back["steps"], int)
    assert write_headline(tmp_path, figures).read_text() == text  # stable bytes for an unchanged run


@pytest.mark.parametrize("bad", [{"a": "text"}, {"a": [1, 2]}, {"a": {"b": {"c": 1}}}, {1: 2.0}])
def test_headline_refuses_what_is_not_a_number_one_level_deep(bad):
    with pytest.raises(TypeError):
        headline_doc(bad)


def test_plot_table_round_trips_with_empty_cells_for_missing(tmp_path):
    rows = [(0, 1.0, "door"), (1, 0.333333333333, "chair"), (2, None, "plant"), (3, float("nan"), "a,b"),
            (4, 1e-9, "x")]
    path = write_plot_table(tmp_path, "loss", ["iteration", "loss", "class"], rows)
    assert path == tmp_path / "plots" / "loss.csv"
    with path.open(newline="") as fh:
        back = list(csv.DictReader(fh))
    assert list(back[0]) == ["iteration", "loss", "class"]
    assert [r["iteration"] for r in back] == ["0", "1", "2", "3", "4"]
    assert [r["loss"] for r in back] == ["1", "0.333333", "", "", "1e-09"]
    assert back[3]["class"] == "a,b"  # quoted, read back whole
    assert math.isclose(float(back[4]["loss"]), 1e-9)
    assert path.read_text().splitlines()[0] == "iteration,loss,class"


def test_plot_table_refuses_ragged_rows_and_odd_names(tmp_path):
    with pytest.raises(ValueError, match="row 1 has 1 cells"):
        plot_table_text(["a", "b"], [(1, 2), (3,)])
    with pytest.raises(ValueError, match="distinct"):
        plot_table_text(["a", "a"], [])
    for name in ("../x", "a/b", "loss.csv", ""):
        with pytest.raises(ValueError, match="plain file name"):
            write_plot_table(tmp_path, name, ["a"], [])


def test_an_interrupted_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    write_headline(tmp_path, {"a": 1.0})
    write_plot_table(tmp_path, "curve", ["x", "y"], [(0, 1)])
    old_json, old_csv = (tmp_path / "headline.json").read_text(), (tmp_path / "plots" / "curve.csv").read_text()

    def broken(fd):
        raise OSError("disk full")

    monkeypatch.setattr("pipeline.io.atomic.os.fsync", broken)
    with pytest.raises(OSError, match="disk full"):
        write_headline(tmp_path, {"a": 2.0})
    with pytest.raises(OSError, match="disk full"):
        write_plot_table(tmp_path, "curve", ["x", "y"], [(0, 2)])
    assert (tmp_path / "headline.json").read_text() == old_json
    assert (tmp_path / "plots" / "curve.csv").read_text() == old_csv
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["curve.csv", "headline.json", "plots"]
