"""Reading the text files a user hands us (CSV tables, YAML, JSON) strictly, with errors that say why.

Every text input is UTF-8 (a UTF-8 byte-order mark is accepted, spreadsheets write one). A file in
another encoding is refused with its encoding named when it can be told (UTF-16/32 by their marks or
zero bytes) or with the line and byte that are not UTF-8. CSV rows must have exactly the header's
fields: a row with more (an unquoted comma in a value) or fewer is an error naming its line, never a row
with shifted labels. Bad input is quoted through `excerpt`, so a huge or binary line stays short.
"""

from __future__ import annotations

import codecs
import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import InputError, Problem, Problems, excerpt

_MARKS = (  # longest first: the UTF-32 LE mark starts with the UTF-16 LE one
    (codecs.BOM_UTF32_LE, "UTF-32 (little-endian)"),
    (codecs.BOM_UTF32_BE, "UTF-32 (big-endian)"),
    (codecs.BOM_UTF16_LE, "UTF-16 (little-endian)"),
    (codecs.BOM_UTF16_BE, "UTF-16 (big-endian)"),
)
SAVE_AS_UTF8 = "save the file as UTF-8 (in a spreadsheet: CSV UTF-8; in an editor: encoding UTF-8)"


def _foreign_encoding(data: bytes) -> str | None:
    """The encoding a file evidently has when it is not UTF-8 (a byte-order mark, or UTF-16's zero bytes)."""
    for mark, name in _MARKS:
        if data.startswith(mark):
            return f"{name}, with a byte-order mark"
    head = data[:200]
    if len(head) >= 4 and head.count(b"\x00") >= len(head) // 4:
        return "UTF-16 or UTF-32 (every other byte is zero)"
    return None


def decode_text(data: bytes, path: Path | str) -> tuple[str | None, Problem | None]:
    """(text, None) for UTF-8 (with or without a byte-order mark), else (None, the problem naming the fix)."""
    foreign = _foreign_encoding(data)
    if foreign is not None:
        return None, Problem(str(path), f"the file is {foreign}, not UTF-8", fix=SAVE_AS_UTF8)
    try:
        return data.decode("utf-8-sig"), None
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        bad = data[exc.start:exc.end]
        hint = " (Latin-1 or Windows-1252?)" if all(0x80 <= b <= 0xFF for b in bad) else ""
        return None, Problem(str(path), f"byte {excerpt(bad)} at offset {exc.start} is not UTF-8{hint}", row=line,
                             fix=SAVE_AS_UTF8)


def read_text(path: Path | str, *, what: str = "file") -> str:
    """The text of a UTF-8 file; InputError naming the file (and the encoding or the bad byte) otherwise."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what}", [Problem(str(path), exc.strerror or str(exc))]) from None
    text, problem = decode_text(data, path)
    if problem is not None:
        raise InputError(f"{path}: the {what} is not UTF-8 text", [problem])
    return text


@dataclass
class CsvTable:
    """A CSV file's stripped header and its rows as (line number, {column: stripped value})."""

    path: Path
    header: list[str]
    rows: list[tuple[int, dict[str, str]]] = field(default_factory=list)


def read_csv(path: Path | str, problems: Problems) -> CsvTable | None:
    """Read a CSV table strictly, adding every bad row to `problems`; None when the file cannot be read.

    Rows with another field count than the header, unterminated quotes and oversized fields are problems
    naming their line; blank lines are skipped; the other rows are returned, so a validator reports them all.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        problems.add(path, f"cannot read: {exc.strerror or exc}")
        return None
    text, problem = decode_text(data, path)
    if problem is not None:
        problems.items.append(problem)
        return None
    # strict: an unterminated quote is an error, not a value; csv's field size limit (128 KiB) refuses a
    # runaway field (a binary file, a missing quote) as an error on its line.
    return _rows(csv.reader(io.StringIO(text, newline=""), strict=True), path, problems)


def _rows(reader, path: Path, problems: Problems) -> CsvTable | None:
    table: CsvTable | None = None
    while True:
        start = reader.line_num + 1
        try:
            fields = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:
            problems.add(path, f"not a CSV row: {excerpt(exc, 120)}", row=start,
                         fix="quote values that hold commas, quotes or line breaks")
            if table is None:
                return None
            continue
        if not fields or (len(fields) == 1 and not fields[0].strip()):
            continue
        if table is None:
            table = CsvTable(path, [h.strip() for h in fields])
            continue
        if len(fields) != len(table.header):
            more = "more" if len(fields) > len(table.header) else "fewer"
            problems.add(path, f"{len(fields)} fields where the header has {len(table.header)} "
                               f"(row {excerpt(','.join(fields))})", row=start,
                         fix=(f"{more} fields than columns: quote a value that holds a comma (\"Room 1, east\")"
                              if more == "more" else "give every column a value (empty between commas)"))
            continue
        table.rows.append((start, {h: v.strip() for h, v in zip(table.header, fields, strict=True)}))
    if table is None:
        problems.add(path, "the file is empty (no header line)", row=1, fix="write the header line and the rows")
    return table
