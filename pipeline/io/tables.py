"""Parquet tables of the pipeline, each with a name and a schema version in its metadata.

A path ending in `.arrow` is an Arrow IPC file instead (uncompressed record batches): the same table,
read memory-mapped, so a database's region descriptors are paged in as a query touches them instead of
loaded whole. Readers refuse a table of another kind or of an unknown major version, and name the file. The
column contracts are the ones in ARCHITECTURE.md; `docs/data-formats.md` documents them for users.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import InputError, Problem
from pipeline.io.atomic import atomic_file

SCHEMA_VERSION = "1.0"
_KIND_KEY = b"siteloc.table"
_VERSION_KEY = b"siteloc.schema_version"

IMAGES = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("stop_id", pa.string(), nullable=False),
        pa.field("view", pa.int32(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("theta", pa.float64(), nullable=False),
        pa.field("room", pa.string()),
        pa.field("area", pa.string()),
        pa.field("split", pa.string(), nullable=False),
        pa.field("width", pa.int32(), nullable=False),
        pa.field("height", pa.int32(), nullable=False),
        pa.field("sha256", pa.string(), nullable=False),
    ]
)

BOXES = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("class_id", pa.int32(), nullable=False),
        pa.field("class_name", pa.string(), nullable=False),
        pa.field("x1", pa.float32(), nullable=False),
        pa.field("y1", pa.float32(), nullable=False),
        pa.field("x2", pa.float32(), nullable=False),
        pa.field("y2", pa.float32(), nullable=False),
    ]
)

# One row per laser scan. Odometry is in the robot's odom frame, ground truth in the map frame.
# A range >= range_max (or non-finite) means "no return".
RUNS = pa.schema(
    [
        pa.field("run", pa.string(), nullable=False),
        pa.field("step", pa.int32(), nullable=False),
        pa.field("t", pa.float64(), nullable=False),
        pa.field("odom_x", pa.float64(), nullable=False),
        pa.field("odom_y", pa.float64(), nullable=False),
        pa.field("odom_theta", pa.float64(), nullable=False),
        pa.field("gt_x", pa.float64()),
        pa.field("gt_y", pa.float64()),
        pa.field("gt_theta", pa.float64()),
        pa.field("ranges", pa.list_(pa.float32()), nullable=False),
        pa.field("angle_min", pa.float32(), nullable=False),
        pa.field("angle_increment", pa.float32(), nullable=False),
        pa.field("range_max", pa.float32(), nullable=False),
        pa.field("image_id", pa.string()),
        pa.field("kidnapped", pa.bool_()),
    ]
)

# Per-step output of `siteloc localize`: one row per (run, trial, step).
ESTIMATES = pa.schema(
    [
        pa.field("run", pa.string(), nullable=False),
        pa.field("trial", pa.int32(), nullable=False),
        pa.field("step", pa.int32(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("theta", pa.float64(), nullable=False),
        pa.field("cov_xx", pa.float64(), nullable=False),
        pa.field("cov_xy", pa.float64(), nullable=False),
        pa.field("cov_yy", pa.float64(), nullable=False),
        pa.field("cov_tt", pa.float64(), nullable=False),
        pa.field("state", pa.string(), nullable=False),
        pa.field("particles", pa.int32(), nullable=False),
        pa.field("updated", pa.bool_(), nullable=False),
        pa.field("best_likelihood", pa.float32(), nullable=False),
        pa.field("update_ms", pa.float32(), nullable=False),
        pa.field("agreement", pa.float32()),
        pa.field("spread_m", pa.float32(), nullable=False),
        pa.field("gt_x", pa.float64()),
        pa.field("gt_y", pa.float64()),
        pa.field("gt_theta", pa.float64()),
        pa.field("error_xy", pa.float64()),
        pa.field("error_theta", pa.float64()),
        pa.field("kidnapped", pa.bool_(), nullable=False),
    ]
)

# Retrieval descriptors (`siteloc extract`): `descriptor` is a fixed_size_list<float32> whose size is the
# descriptor's dimension (the contract says "list"; each file fixes the size, readers check it is fixed).
IPA = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("descriptor", pa.list_(pa.float32()), nullable=False),
    ]
)

# One row per region of an image: RPN proposals and detections, boxes in original pixels.
RPA = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("region", pa.int32(), nullable=False),
        pa.field("source", pa.string(), nullable=False),  # "proposal" or "detection"
        pa.field("x1", pa.float32(), nullable=False),
        pa.field("y1", pa.float32(), nullable=False),
        pa.field("x2", pa.float32(), nullable=False),
        pa.field("y2", pa.float32(), nullable=False),
        pa.field("score", pa.float32(), nullable=False),
        pa.field("class_id", pa.int32(), nullable=False),  # 0 for proposals
        pa.field("descriptor", pa.list_(pa.float32()), nullable=False),
    ]
)

# The images an extraction covered, with their poses (map frame): mapping stops and run frames.
CATALOG = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("theta", pa.float64(), nullable=False),
        pa.field("group", pa.string(), nullable=False),  # the stop or the run
        pa.field("split", pa.string(), nullable=False),  # the ingest split; "run:<name>" for run frames
    ]
)

# One row per camera frame of a run (`siteloc frame-features`): a pretrained classifier's 1000 logits,
# the input of the sequence LSTM (seed 000 section 3.3), with the frame's ground-truth pose when known.
FRAMES = pa.schema(
    [
        pa.field("run", pa.string(), nullable=False),
        pa.field("step", pa.int32(), nullable=False),
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("gt_x", pa.float64()),
        pa.field("gt_y", pa.float64()),
        pa.field("gt_theta", pa.float64()),
        pa.field("descriptor", pa.list_(pa.float32()), nullable=False),
    ]
)

# The sequence database (`siteloc train-sequence`): one PCA-whitened LSTM descriptor per window of
# consecutive mapping-run frames, with the pose of the window's last frame.
SEQUENCES = pa.schema(
    [
        pa.field("run", pa.string(), nullable=False),
        pa.field("end_step", pa.int32(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("theta", pa.float64(), nullable=False),
        pa.field("descriptor", pa.list_(pa.float32()), nullable=False),
    ]
)

# Seed 001's per-layer image vectors (`siteloc prior features`: one file per CNN layer, raw; `prior build`:
# the database, compressed), with the image's pose and its (room, area) class.
MULTILAYER = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("stop_id", pa.string(), nullable=False),
        pa.field("room", pa.string(), nullable=False),
        pa.field("area", pa.string(), nullable=False),
        pa.field("split", pa.string(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("theta", pa.float64(), nullable=False),
        pa.field("descriptor", pa.list_(pa.float32()), nullable=False),
    ]
)

# The content hash of every image an extraction described, so a later one can reuse its rows (`extract --reuse`).
IMAGE_HASHES = pa.schema(
    [
        pa.field("image_id", pa.string(), nullable=False),
        pa.field("sha256", pa.string(), nullable=False),
    ]
)

SCHEMAS: dict[str, pa.Schema] = {"images": IMAGES, "boxes": BOXES, "runs": RUNS, "estimates": ESTIMATES,
                                 "ipa": IPA, "rpa": RPA, "catalog": CATALOG, "frames": FRAMES,
                                 "sequences": SEQUENCES, "multilayer": MULTILAYER, "prior_db": MULTILAYER,
                                 "image_hashes": IMAGE_HASHES}


def _contract(kind: str, table: pa.Table | None = None) -> pa.Schema:
    """The kind's schema; a `descriptor` column takes the fixed size of the table's own column."""
    schema = SCHEMAS[kind]
    if "descriptor" in schema.names and table is not None and "descriptor" in table.column_names:
        found = table.schema.field("descriptor").type
        if pa.types.is_fixed_size_list(found):
            i = schema.get_field_index("descriptor")
            schema = schema.set(i, pa.field("descriptor", pa.list_(pa.float32(), found.list_size), nullable=False))
    return schema


def descriptor_array(matrix) -> pa.FixedSizeListArray:
    """An (N, D) float matrix as a fixed_size_list<float32>[D] column."""
    import numpy as np

    m = np.ascontiguousarray(matrix, dtype=np.float32)
    if m.ndim != 2:
        raise ValueError(f"descriptors must be a 2-D array, got shape {m.shape}")
    return pa.FixedSizeListArray.from_arrays(pa.array(m.reshape(-1)), m.shape[1])


def descriptor_chunks(table: pa.Table) -> list:
    """The `descriptor` column as one (n_k, D) float32 array per chunk of the table, none copied where the
    table is a memory-mapped `.arrow` file (one chunk per record batch)."""
    import numpy as np

    chunked = table.column("descriptor")
    size = chunked.type.list_size
    return [np.asarray(c.values.to_numpy(zero_copy_only=False), dtype=np.float32).reshape(-1, size)
            for c in chunked.chunks] or [np.zeros((0, size), np.float32)]


def descriptor_matrix(table: pa.Table):
    """The `descriptor` column of a table as an (N, D) float32 numpy array (no copy when possible: a view on a
    memory-mapped `.arrow` table, read-only)."""
    import numpy as np

    chunked = table.column("descriptor")
    col = chunked.chunk(0) if chunked.num_chunks == 1 else chunked.combine_chunks()  # combine copies even one chunk
    size = col.type.list_size
    return np.asarray(col.values.to_numpy(zero_copy_only=False), dtype=np.float32).reshape(-1, size)


def _with_metadata(schema: pa.Schema, kind: str, extra: dict[str, str] | None) -> pa.Schema:
    meta = {_KIND_KEY: kind.encode(), _VERSION_KEY: SCHEMA_VERSION.encode()}
    for k, v in (extra or {}).items():
        meta[f"siteloc.{k}".encode()] = str(v).encode()
    return schema.with_metadata(meta)


def list_column(rows: np.ndarray) -> pa.ListArray:
    """A (N, B) array as a list column of N rows, from its buffer (not through N Python lists)."""
    rows = np.ascontiguousarray(rows)
    n, b = rows.shape
    return pa.ListArray.from_arrays(pa.array(np.arange(0, n * b + 1, b, dtype=np.int32)), pa.array(rows.ravel()))


def to_table(kind: str, columns: dict, metadata: dict[str, str] | None = None) -> pa.Table:
    """Build a table of `kind` from column arrays, cast to the contract's types."""
    schema = SCHEMAS[kind]
    missing = [f.name for f in schema if f.name not in columns]
    if missing:
        raise KeyError(f"{kind} table is missing columns {missing}")
    arrays = [columns[f.name] if isinstance(columns[f.name], pa.FixedSizeListArray) else
              columns[f.name].cast(f.type) if isinstance(columns[f.name], pa.Array) else
              pa.array(columns[f.name], type=f.type) for f in schema]
    schema = pa.schema([pa.field(f.name, a.type, nullable=f.nullable) for f, a in zip(schema, arrays, strict=True)])
    return pa.Table.from_arrays(arrays, schema=_with_metadata(schema, kind, metadata))


def write_table(path: Path, table: pa.Table, kind: str, metadata: dict[str, str] | None = None) -> Path:
    """Write `table` (cast to the `kind` contract) atomically with zstd compression."""
    merged = {k: v for k, v in table_metadata(table).items() if k not in ("table", "schema_version")}
    merged.update(metadata or {})
    schema = _with_metadata(_contract(kind, table), kind, merged)
    table = table.select(schema.names).cast(schema)
    with atomic_file(Path(path), "wb") as fh:
        if Path(path).suffix == ".arrow":
            with pa.ipc.new_file(fh, schema) as writer:
                writer.write_table(table.combine_chunks(), max_chunksize=max(table.num_rows, 1))
        else:
            pq.write_table(table, fh, compression="zstd")
    return Path(path)


def write_table_parts(path: Path, parts: Iterable[pa.Table], kind: str, metadata: dict[str, str] | None = None
                      ) -> int:
    """Write the concatenation of `parts` as `write_table` would, one part in memory at a time (a Parquet row
    group each; an Arrow IPC record batch each). Returns the rows written; at least one part is needed."""
    writer, rows = None, 0
    with atomic_file(Path(path), "wb") as fh:
        try:
            for part in parts:
                if writer is None:
                    merged = {k: v for k, v in table_metadata(part).items() if k not in ("table", "schema_version")}
                    merged.update(metadata or {})
                    schema = _with_metadata(_contract(kind, part), kind, merged)
                    writer = (pa.ipc.new_file(fh, schema) if Path(path).suffix == ".arrow"
                              else pq.ParquetWriter(fh, schema, compression="zstd"))
                part = part.select(schema.names).cast(schema)
                if isinstance(writer, pq.ParquetWriter):
                    writer.write_table(part, row_group_size=max(part.num_rows, 1))
                else:
                    writer.write_table(part)
                rows += part.num_rows
            if writer is None:
                raise ValueError(f"{path}: no parts to write")
        finally:
            if writer is not None:
                writer.close()
    return rows


def table_metadata(table: pa.Table) -> dict[str, str]:
    """The `siteloc.*` metadata of a table, without the prefix."""
    return {
        k.decode()[len("siteloc.") :]: v.decode()
        for k, v in (table.schema.metadata or {}).items()
        if k.startswith(b"siteloc.")
    }


def read_table(path: Path, kind: str) -> pa.Table:
    """Read a table and check its kind, major schema version and columns."""
    path = Path(path)
    _exists(path, kind)
    arrow = path.suffix == ".arrow"
    try:
        table = pa.ipc.open_file(pa.memory_map(str(path))).read_all() if arrow else pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(f"{path}: not a readable {'Arrow IPC' if arrow else 'Parquet'} file",
                         [Problem(str(path), str(exc))]) from None
    _check_schema(path, kind, table.schema)
    meta = table.schema.metadata or {}
    contract = _contract(kind, table)
    return table.select(contract.names).cast(_with_metadata(contract, kind, None).with_metadata(meta))


def read_table_batches(path: Path, kind: str):
    """The record batches of an Arrow IPC table (`.arrow`) one at a time, each checked and cast as
    `read_table` casts the whole; read, not mapped, so a table larger than memory is never held whole."""
    path = Path(path)
    _exists(path, kind)
    try:
        reader = pa.ipc.open_file(pa.OSFile(str(path)))
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(f"{path}: not a readable Arrow IPC file", [Problem(str(path), str(exc))]) from None
    _check_schema(path, kind, reader.schema)
    contract = _contract(kind, reader.schema.empty_table())
    schema = _with_metadata(contract, kind, None).with_metadata(reader.schema.metadata or {})
    for i in range(reader.num_record_batches):
        try:
            batch = reader.get_batch(i)
        except (pa.ArrowInvalid, OSError) as exc:
            raise InputError(f"{path}: not a readable Arrow IPC file", [Problem(f"{path} record batch {i}",
                                                                                str(exc))]) from None
        yield pa.Table.from_batches([batch]).select(contract.names).cast(schema)


def read_table_schema(path: Path, kind: str) -> pa.Schema:
    """The schema of a Parquet table, checked as `read_table` checks it, without reading its rows."""
    path = Path(path)
    _exists(path, kind)
    try:
        schema = pq.read_schema(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(f"{path}: not a readable Parquet file", [Problem(str(path), str(exc))]) from None
    _check_schema(path, kind, schema)
    return schema


def _exists(path: Path, kind: str) -> None:
    if not path.is_file():
        raise InputError(
            f"{path}: {kind} table not found",
            [Problem(str(path), "file is missing", fix="run the stage that writes it")],
        )


def _check_schema(path: Path, kind: str, schema: pa.Schema) -> None:
    """Kind, major schema version and columns of a table's schema; InputError naming the file otherwise."""
    meta = schema.metadata or {}
    found_kind = meta.get(_KIND_KEY, b"").decode()
    version = meta.get(_VERSION_KEY, b"").decode()
    problems = []
    if found_kind != kind:
        problems.append(Problem(str(path), f"holds a '{found_kind or 'unknown'}' table, expected '{kind}'"))
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        problems.append(
            Problem(
                str(path),
                f"schema version '{version or 'none'}' is not readable by this siteloc (reads {SCHEMA_VERSION})",
                fix="re-run the stage that wrote it with this version",
            )
        )
    missing = [n for n in SCHEMAS[kind].names if n not in schema.names]
    if missing:
        problems.append(Problem(str(path), f"missing columns {missing}"))
    elif "descriptor" in SCHEMAS[kind].names and not pa.types.is_fixed_size_list(schema.field("descriptor").type):
        problems.append(Problem(str(path), "column 'descriptor' is not a fixed_size_list<float32>",
                                fix="re-run `siteloc extract` with this version"))
    if problems:
        raise InputError(f"{path}: not a valid {kind} table", problems)
