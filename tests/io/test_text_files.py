"""Strict text inputs: CSV rows with the header's field count, UTF-8 only, problems naming line and encoding."""

from __future__ import annotations

import codecs
import csv
import io

import pytest

from pipeline.errors import InputError, Problems
from pipeline.io.text_files import read_csv, read_text

HEADER = "image,stop_id,view,x,y,theta,room\n"


def problems_of(path) -> tuple[object, Problems]:
    problems = Problems()
    return read_csv(path, problems), problems


def test_valid_file_reads_as_csv_dictreader_does(tmp_path):
    text = HEADER + 'a.jpg,s0,0,1.5,2,0.1,"Room 1, east"\n\nb.jpg,s1,1,3,4,0.2," lab "\n'
    path = tmp_path / "c.csv"
    path.write_text(text)
    table, problems = problems_of(path)
    assert not problems and not problems.warnings
    twin = [{k: v.strip() for k, v in row.items()} for row in csv.DictReader(io.StringIO(text))]
    assert [rec for _, rec in table.rows] == twin
    assert [line for line, _ in table.rows] == [2, 4]  # the blank line 3 is skipped, numbering is not


def test_row_with_an_extra_field_is_an_error_naming_its_line(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text(HEADER + "a.jpg,s0,0,1,2,0,lab\nb.jpg,s1,1,3,4,0,Room 2, west\nc.jpg,s2,2,5,6,0,\n")
    table, problems = problems_of(path)
    assert [p.row for p in problems.items] == [3]
    text = str(problems.items[0])
    assert "8 fields where the header has 7" in text and "quote a value" in text
    assert [line for line, _ in table.rows] == [2, 4]  # the others still parse, so all problems are reported


def test_row_with_too_few_fields_is_an_error(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text(HEADER + "a.jpg,s0,0,1,2\n")
    _, problems = problems_of(path)
    assert problems.items[0].row == 2 and "5 fields where the header has 7" in problems.items[0].message


def test_line_numbers_count_quoted_line_breaks(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text(HEADER + 'a.jpg,s0,0,1,2,0,"two\nlines"\nb.jpg,s1,1,3,4,0\n')
    _, problems = problems_of(path)
    assert [p.row for p in problems.items] == [4]


def test_unterminated_quote_and_huge_field_are_errors_with_short_messages(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text(HEADER + "a.jpg,s0,0,1,2,0,\"" + "x" * 10_000_000 + "\n")
    _, problems = problems_of(path)
    assert len(problems.items) == 1 and problems.items[0].row == 2
    assert len(str(problems.items[0])) < 400


def test_utf8_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "c.csv"
    path.write_bytes(codecs.BOM_UTF8 + (HEADER + "a.jpg,s0,0,1,2,0,Küche\n").encode())
    table, problems = problems_of(path)
    assert not problems and table.header[0] == "image" and table.rows[0][1]["room"] == "Küche"


@pytest.mark.parametrize("encoding, named", [("utf-16", "UTF-16 (little-endian), with a byte-order mark"),
                                             ("utf-16-be", "every other byte is zero"),
                                             ("utf-32", "UTF-32 (little-endian)")])
def test_utf16_and_utf32_are_refused_by_name(tmp_path, encoding, named):
    path = tmp_path / "c.csv"
    path.write_bytes((HEADER + "a.jpg,s0,0,1,2,0,lab\n").encode(encoding))
    table, problems = problems_of(path)
    assert table is None and named in problems.items[0].message and "UTF-8" in problems.items[0].fix


def test_latin1_byte_names_line_and_offset(tmp_path):
    path = tmp_path / "c.csv"
    data = (HEADER + "a.jpg,s0,0,1,2,0,lab\nb.jpg,s1,1,3,4,0,").encode() + "Küche\n".encode("latin-1")
    path.write_bytes(data)
    table, problems = problems_of(path)
    p, offset = problems.items[0], data.index("ü".encode("latin-1"))
    assert table is None and p.row == 3 and f"offset {offset}" in p.message and "Latin-1" in p.message


def test_empty_file_and_escape_bytes(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text("")
    _, problems = problems_of(path)
    assert "empty" in problems.items[0].message
    path.write_text(HEADER + "a.jpg,s0,0,1,2,0,\x1b[2Jboom,extra\n")
    _, problems = problems_of(path)
    assert "\x1b" not in str(problems.items[0]) and "\\x1b[2J" in str(problems.items[0])


def test_read_text_names_the_encoding(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_bytes("name: tiny\n".encode("utf-16"))
    with pytest.raises(InputError, match="UTF-16") as exc:
        read_text(path, what="site description")
    assert str(path) in str(exc.value)
    path.write_bytes(codecs.BOM_UTF8 + b"name: tiny\n")
    assert read_text(path) == "name: tiny\n"
