"""Readers for the stages' DVC files (headline.json, plots/<name>.csv) in tests, as DVC reads them."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest


def read_headline(out: Path) -> dict:
    text = (Path(out) / "headline.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    doc = json.loads(text)
    for v in doc.values():  # numbers or null, nested at most one level
        for x in (v.values() if isinstance(v, dict) else [v]):
            assert x is None or (isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)), doc
    return doc


def read_plot(out: Path, name: str, columns: list[str]) -> list[dict]:
    """The rows of plots/<name>.csv, after checking its header is exactly `columns`; empty cells as None,
    numbers as floats, other cells as text."""
    with (Path(out) / "plots" / f"{name}.csv").open(newline="") as fh:
        reader = csv.reader(fh)
        assert next(reader) == columns
        rows = list(reader)
    assert rows and all(len(r) == len(columns) for r in rows)

    def value(cell: str):
        if cell == "":
            return None
        try:
            return float(cell)
        except ValueError:
            return cell

    return [{c: value(v) for c, v in zip(columns, r, strict=True)} for r in rows]


def approx(v):
    """What a figure reads back as: rounded to 6 significant digits (None stays None)."""
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else pytest.approx(v, rel=1e-5,
                                                                                                     abs=1e-12)
