"""`siteloc ingest` under a careless or hostile hand: refused with exit 1, a short readable message, inputs
untouched and nothing written; never `error: unexpected`, never a row accepted with shifted labels."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from stages.app import app
from tests.fixtures.capture_site import write_capture_site

runner = CliRunner()


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_capture_site(tmp_path_factory.mktemp("pristine") / "site")


@pytest.fixture
def site(pristine, tmp_path) -> Path:
    dst = tmp_path / "work" / "site"
    shutil.copytree(pristine, dst)
    return dst


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def append_row(site: Path, raw: bytes) -> None:
    with (site / "captures.csv").open("ab") as fh:
        fh.write(raw)


def extra_field(site):  # an unquoted comma in a room name: room and area would shift one column
    csv = site / "captures.csv"
    csv.write_bytes(csv.read_bytes().replace(b",room_a,west", b",room_a, east wing,west", 1))


def latin1(site):
    data = (site / "captures.csv").read_bytes().replace(b"\n", " K\xfcche\n".encode("latin-1"), 1)
    (site / "captures.csv").write_bytes(data)


def utf16(site):
    text = (site / "captures.csv").read_text()
    (site / "captures.csv").write_bytes(text.encode("utf-16"))


def garbage_line(site):
    append_row(site, b"\x1b[31m" + b"A" * 10_000_000 + b"\n")


CASES = {  # name -> (break the site, words the message must hold)
    "extra field": (extra_field, ["captures.csv, line 2", "fields where the header has", "quote a value"]),
    "Latin-1 byte": (latin1, ["captures.csv", "line 1", "not UTF-8", "Latin-1"]),
    "UTF-16": (utf16, ["captures.csv", "UTF-16", "save the file as UTF-8"]),
    "10 MB escape line": (garbage_line, ["captures.csv"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_captures_csv_is_refused_cleanly(site, case):
    breaker, words = CASES[case]
    breaker(site)
    before = snapshot(site.parent)
    result = runner.invoke(app, ["ingest", str(site), "--out", str(site.parent / "out"), "--config", "ci"])
    assert result.exit_code == 1, result.output
    assert "unexpected" not in result.output and "Traceback" not in result.output
    assert "\x1b" not in result.output and len(result.output) < 4000
    for word in words:
        assert word in result.output, result.output
    assert snapshot(site.parent) == before  # inputs untouched, no output, no temporary left


@pytest.mark.parametrize("rel", ["site", "site/images", "site/ingested", "."])
def test_output_overlapping_the_site_is_refused_even_with_force(site, rel):
    before = snapshot(site.parent)
    out = site.parent / rel
    result = runner.invoke(app, ["ingest", str(site), "--out", str(out), "--config", "ci", "--force"])
    assert result.exit_code == 1 and "unexpected" not in result.output
    assert "Nothing was written" in result.output and "give --out a separate path" in result.output
    assert snapshot(site.parent) == before
