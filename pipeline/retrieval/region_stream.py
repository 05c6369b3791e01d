"""An extraction's regions read a record batch at a time: `build-index` of a site of 10^6 images.

rpa.parquet holds about 100 regions an image (~45 KB): 45 GB at 10^6 images, more than a machine's memory.
`build-index` needs three passes over them, none of which has to hold them all: the images' region offsets
(from the image_id column only), the rows sampled to fit the RPA whitening, and the whitened regions of the
database images, written batch after batch into database_rpa.arrow (`tables.write_table_parts`), which
`load_database` memory-maps (`search.ChunkedRows` reads across its batches).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem

BATCH_ROWS = 16_384  # regions per pass step: ~7 MB of 112-d float32
READ_BUFFER = 4 << 20  # bytes read ahead; pyarrow's default pre-buffers whole row groups (4x the data here)


def _file(path: Path):
    import pyarrow.parquet as pq

    from pipeline.io import tables

    tables.read_table_schema(path, "rpa")  # kind and version checked as read_table does
    return pq.ParquetFile(path, pre_buffer=False, buffer_size=READ_BUFFER)


def region_offsets_streamed(path: Path, image_ids: list[str]) -> np.ndarray:
    """(N + 1,) offsets of each image's regions in rpa.parquet at `path`, grouped in `image_ids` order."""
    import pyarrow as pa
    import pyarrow.compute as pc

    value_set = pa.array(image_ids, type=pa.string())
    counts = np.zeros(len(image_ids), dtype=np.int64)
    last = -1
    for batch in _file(path).iter_batches(batch_size=BATCH_ROWS, columns=["image_id"]):
        owner = pc.index_in(batch.column(0), value_set=value_set)
        if owner.null_count:
            _disorder(path, "regions of images the catalog does not list")
        owner = owner.to_numpy().astype(np.int64, copy=False)
        if len(owner) and (owner[0] < last or np.any(np.diff(owner) < 0)):
            _disorder(path, "rows are not grouped by image in the catalog's order")
        counts += np.bincount(owner, minlength=len(image_ids))
        last = int(owner[-1]) if len(owner) else last
    return np.concatenate([[0], np.cumsum(counts)])


def _disorder(path: Path, why: str):
    raise InputError(f"{path}: {why}", [Problem(str(path), why, fix="re-run `siteloc extract`")])


def read_rows(path: Path, rows: np.ndarray) -> np.ndarray:
    """The descriptors of the region rows `rows` (sorted, ascending) of rpa.parquet, (len(rows), D)."""
    import pyarrow as pa

    from pipeline.io import tables

    out, start = [], 0
    rows = np.asarray(rows, dtype=np.int64)
    for batch in _file(path).iter_batches(batch_size=BATCH_ROWS, columns=["descriptor"]):
        stop = start + batch.num_rows
        lo, hi = np.searchsorted(rows, [start, stop])
        if hi > lo:
            out.append(tables.descriptor_matrix(pa.Table.from_batches([batch]))[rows[lo:hi] - start])
        start = stop
    dim = _file(path).schema_arrow.field("descriptor").type.list_size
    return np.vstack(out) if out else np.zeros((0, dim), np.float32)


def whitened_parts(path: Path, offsets: np.ndarray, keep: np.ndarray, transform: Callable[[np.ndarray], np.ndarray]
                   ) -> Iterator:
    """Tables of the regions of the images where `keep` is true, in file order, their descriptors replaced by
    `transform(descriptors)`: one per record batch of rpa.parquet."""
    import pyarrow as pa


    start, written, table = 0, 0, None
    for batch in _file(path).iter_batches(batch_size=BATCH_ROWS):
        stop = start + batch.num_rows
        image = np.searchsorted(offsets, np.arange(start, stop), side="right") - 1
        table = pa.Table.from_batches([batch]).filter(pa.array(keep[image]))
        start = stop
        if table.num_rows or not written and start == offsets[-1]:  # at least one part, if only an empty one
            written += 1
            yield _whitened(table, transform)
    if not written:  # a file without row groups
        schema = _file(path).schema_arrow
        yield _whitened(schema.empty_table(), transform)


def _whitened(table, transform):
    from pipeline.io import tables

    dim = table.schema.field("descriptor").type.list_size
    desc = transform(tables.descriptor_matrix(table) if table.num_rows else np.zeros((1, dim), np.float32))
    desc = desc[:table.num_rows]
    return table.set_column(table.schema.get_field_index("descriptor"), "descriptor",
                            tables.descriptor_array(np.ascontiguousarray(desc, dtype=np.float32)))
