"""Scans as rows read a block at a time, so a long recording's ranges are never all in memory.

`ScanRows` gives what a replay needs of a (T, B) float32 array: `len`, `shape`, a row, a run of rows
as an array, and lazy views (a subset of rows, the beams reversed). It reads blocks from a source and
keeps the last one. Two sources: `ScanSpool`, an unnamed temporary file filled one scan at a time
(`read_recording`), and the record batches of an Arrow IPC runs table (`ipc_rows`). Both are read
with plain reads (`os.preadv`, Arrow's file reader), not a memory map, because mapped pages count in
the process's memory once touched.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem

#: Rows per block of a spool (and per record batch of a runs table written in parts).
BLOCK_ROWS = 1024


class _SpoolSource:
    """Blocks of a spool file: fixed-size runs of float32 rows."""

    def __init__(self, fh, rows: int, width: int, block_rows: int):
        self.fh, self.width, self.block_rows = fh, width, block_rows
        self.starts = np.r_[np.arange(0, rows, block_rows), rows].astype(np.int64)

    def block(self, b: int) -> np.ndarray:
        a, e = int(self.starts[b]), int(self.starts[b + 1])
        out = np.empty((e - a, self.width), np.float32)
        got = os.preadv(self.fh.fileno(), [memoryview(out).cast("B")], a * self.width * 4)
        if got != out.nbytes:
            raise OSError(f"scan spool: read {got} of {out.nbytes} bytes at row {a}")
        return out


class _IpcSource:
    """Blocks of an Arrow IPC file: its record batches' list<float32> column, one batch a block."""

    def __init__(self, path: Path, column: str, starts: np.ndarray, width: int):
        import pyarrow as pa

        self.path, self.column, self.starts, self.width = Path(path), column, starts, width
        self._reader = pa.ipc.open_file(pa.OSFile(str(path)))

    def block(self, b: int) -> np.ndarray:
        col = self._reader.get_batch(b).column(self.column)
        return batch_rows(self.path, col, self.width, first_row=int(self.starts[b]))


def batch_rows(path: Path, column, width: int | None, first_row: int = 0) -> np.ndarray:
    """A list<float32> column (one batch) as (N, B) float32; every list must have B entries."""
    lengths = np.asarray(column.value_lengths().fill_null(-1))
    if len(lengths) and (width is None):
        width = int(lengths[0])
    bad = np.nonzero(lengths != width)[0]
    if len(bad):
        raise InputError(f"{path}: scans of different lengths", [Problem(
            f"{path} row {first_row + int(bad[0])}", f"{int(lengths[bad[0]])} beams where the run's scans have "
            f"{width}", fix="every scan of a run must have the same beams")])
    values = column.flatten().to_numpy(zero_copy_only=False).astype(np.float32, copy=False)
    return values.reshape(len(column), width or 0)


class ScanRows:
    """A (T, B) float32 array read a block at a time (see module docstring). Indexing: an int gives a row,
    a slice (or a slice and columns) an array, an int or bool array of rows a lazy view of those rows, and
    `rows[..., ::-1]` a lazy view with the beams reversed; any other index, and `np.asarray(rows)`, reads
    them all."""

    ndim = 2
    dtype = np.dtype(np.float32)

    def __init__(self, source, index: np.ndarray | None = None, reverse: bool = False):
        self._source, self._index, self._reverse = source, index, reverse
        self._cached: tuple[int, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self._source.starts[-1]) if self._index is None else len(self._index)

    @property
    def shape(self) -> tuple[int, int]:
        return len(self), self._source.width

    @property
    def blocks_held(self) -> int:
        """Blocks held in memory (at most one)."""
        return int(self._cached is not None)

    def _block(self, b: int) -> np.ndarray:
        if self._cached is None or self._cached[0] != b:
            self._cached = None  # drop the old block before reading the next
            self._cached = (b, self._source.block(b))
        return self._cached[1]

    def _take(self, src: np.ndarray) -> np.ndarray:
        """Rows at source positions `src`, in that order."""
        out = np.empty((len(src), self._source.width), np.float32)
        blocks = np.searchsorted(self._source.starts, src, side="right") - 1
        cut = np.r_[0, np.nonzero(np.diff(blocks))[0] + 1, len(src)]
        for a, e in zip(cut[:-1], cut[1:], strict=True):  # runs of one block
            if e > a:
                b = int(blocks[a])
                out[a:e] = self._block(b)[src[a:e] - self._source.starts[b]]
        return out[:, ::-1] if self._reverse else out

    def _positions(self, key) -> np.ndarray:
        n = len(self)
        logical = np.arange(n)[key]
        return logical if self._index is None else self._index[logical]

    def __getitem__(self, key):
        if isinstance(key, (int, np.integer)):
            i = int(key) + (len(self) if key < 0 else 0)
            if not 0 <= i < len(self):
                raise IndexError(f"row {key} of {len(self)}")
            src = i if self._index is None else int(self._index[i])
            b = int(np.searchsorted(self._source.starts, src, side="right") - 1)
            row = self._block(b)[src - self._source.starts[b]]
            return row[::-1] if self._reverse else row
        if isinstance(key, slice):
            return self._take(self._positions(key))
        if isinstance(key, tuple) and len(key) == 2:
            if key[0] is Ellipsis and key[1] == slice(None, None, -1):
                return ScanRows(self._source, self._index, not self._reverse)
            if isinstance(key[0], slice):
                return self[key[0]][:, key[1]]
        if not isinstance(key, tuple):
            arr = np.asarray(key)
            if arr.ndim == 1 and (arr.dtype.kind in "iu" or (arr.dtype == bool and len(arr) == len(self))):
                return ScanRows(self._source, self._positions(arr), self._reverse)
        return np.asarray(self)[key]  # anything else numpy takes, on the rows read whole

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __array__(self, dtype=None, copy=None):
        out = self._take(self._positions(slice(None)))
        return out if dtype is None else out.astype(dtype, copy=False)

    def chunks(self, rows: int = BLOCK_ROWS):
        """(start, array) of consecutive runs of `rows` rows."""
        for a in range(0, len(self), rows):
            yield a, self[a: a + rows]


class ScanSpool:
    """Scans appended one at a time to an unnamed temporary file (deleted when closed, even after a
    crash); `rows()` reads them back. Memory: one block of rows being filled."""

    def __init__(self, block_rows: int = BLOCK_ROWS):
        self.block_rows, self.width, self.n = block_rows, None, 0
        self._fh = tempfile.TemporaryFile(prefix="siteloc-scans-")
        self._buf: np.ndarray | None = None
        self._fill = 0

    def append(self, row: np.ndarray) -> None:
        row = np.asarray(row, dtype=np.float32).reshape(-1)
        if self.width is None:
            self.width = len(row)
            self._buf = np.empty((self.block_rows, self.width), np.float32)
        if len(row) != self.width:
            raise ValueError(f"a row of {len(row)} values in a spool of {self.width}")
        self._buf[self._fill] = row
        self._fill += 1
        self.n += 1
        if self._fill == self.block_rows:
            self._flush()

    def _flush(self) -> None:
        if self._fill:
            self._fh.write(self._buf[: self._fill].tobytes())
            self._fill = 0

    def __len__(self) -> int:
        return self.n

    def rows(self) -> ScanRows:
        """The rows appended so far (the spool stays open for the rows to be read)."""
        self._flush()
        self._fh.flush()
        return ScanRows(_SpoolSource(self._fh, self.n, self.width or 0, self.block_rows))


def ipc_rows(path: Path, column: str, batch_lengths: list[int], width: int) -> ScanRows:
    """The list<float32> `column` of an Arrow IPC file whose record batches have `batch_lengths` rows."""
    starts = np.r_[0, np.cumsum(batch_lengths)].astype(np.int64)
    return ScanRows(_IpcSource(path, column, starts, width))
