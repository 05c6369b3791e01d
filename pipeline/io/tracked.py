"""What DVC compares across runs: `headline.json` and `plots/<name>.csv` inside a stage's output directory.

`dvc metrics diff` reads `headline.json`, a small JSON object of the few figures people compare across
retrains (numbers, or objects of numbers: nested at most one level); `dvc plots diff` reads the CSV tables
under `plots/` (a header row, then one row per point). Both are written atomically (write, then rename)
and every float is rounded to 6 significant digits, so that a rerun that changes nothing writes the
same bytes and a change shows as a short diff. A missing or non-finite figure is `null` in the JSON
(never `NaN`, which JSON does not have) and an empty cell in a CSV.
"""

from __future__ import annotations

import csv
import io
import json
import math
import numbers
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from pipeline.io.atomic import write_text_atomic

HEADLINE = "headline.json"
PLOTS = "plots"
SIGNIFICANT = 6

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _number(v, where: str):
    """v as a JSON number (floats to SIGNIFICANT digits) or None for missing / NaN / inf."""
    if v is None:
        return None
    if isinstance(v, bool):  # before Integral: a bool is an int to Python, not a figure to DVC
        return int(v)
    if isinstance(v, numbers.Integral):
        return int(v)
    if isinstance(v, numbers.Real):
        f = float(v)
        if not math.isfinite(f):
            return None
        return float(f"{f:.{SIGNIFICANT}g}")
    raise TypeError(f"{where}: {v!r} is not a number (headline figures are numbers or null)")


def headline_doc(figures: Mapping) -> dict:
    """`figures` cleaned for headline.json: numbers rounded, NaN / inf / None as None, at most one level of
    nesting; anything else (strings, lists, deeper objects) is a TypeError."""
    out = {}
    for k, v in figures.items():
        if not isinstance(k, str):
            raise TypeError(f"headline key {k!r} is not a string")
        if isinstance(v, Mapping):
            inner = {}
            for k2, v2 in v.items():
                if not isinstance(k2, str):
                    raise TypeError(f"headline key {k}.{k2!r} is not a string")
                if isinstance(v2, Mapping):
                    raise TypeError(f"headline {k}.{k2}: nested more than one level")
                inner[k2] = _number(v2, f"headline {k}.{k2}")
            out[k] = inner
        else:
            out[k] = _number(v, f"headline {k}")
    return out


def write_headline(out_dir: Path, figures: Mapping) -> Path:
    """Write `out_dir/headline.json` (see `headline_doc`) atomically; returns its path."""
    text = json.dumps(headline_doc(figures), indent=2, allow_nan=False) + "\n"
    return write_text_atomic(Path(out_dir) / HEADLINE, text)


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        f = float(v)
        return f"{f:.{SIGNIFICANT}g}" if math.isfinite(f) else ""
    return str(v)


def plot_table_text(columns: Sequence[str], rows: Iterable[Sequence]) -> str:
    """The CSV text of a plot table: the header, then one line per row (None / NaN / inf: empty cells)."""
    columns = list(columns)
    if not columns or len(set(columns)) != len(columns) or not all(isinstance(c, str) and c for c in columns):
        raise ValueError(f"plot table columns must be distinct non-empty names, not {columns}")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for i, row in enumerate(rows):
        row = list(row)
        if len(row) != len(columns):
            raise ValueError(f"plot table row {i} has {len(row)} cells for {len(columns)} columns {columns}")
        w.writerow([_cell(v) for v in row])
    return buf.getvalue()


def write_plot_table(out_dir: Path, name: str, columns: Sequence[str], rows: Iterable[Sequence]) -> Path:
    """Write `out_dir/plots/<name>.csv` atomically; returns its path."""
    if not _NAME.match(name) or name.endswith(".csv"):
        raise ValueError(f"plot table name {name!r}: a plain file name without .csv")
    return write_text_atomic(Path(out_dir) / PLOTS / f"{name}.csv", plot_table_text(columns, rows))
