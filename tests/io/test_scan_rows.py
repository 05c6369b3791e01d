"""ScanRows against its numpy twin: the same rows, slices and views, read a block at a time."""

import numpy as np
import pyarrow as pa
import pytest

from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.io.capture_runs import CaptureRun
from pipeline.io.scan_rows import ScanRows, ScanSpool, ipc_rows
from pipeline.io.site import Laser


def spooled(array: np.ndarray, block_rows: int) -> ScanRows:
    spool = ScanSpool(block_rows=block_rows)
    for row in array:
        spool.append(row)
    return spool.rows()


@pytest.fixture
def twin():
    rng = np.random.default_rng(0)
    array = rng.random((1000, 7), dtype=np.float32)
    array[5, 2], array[700, 0] = np.nan, np.inf
    return array, spooled(array, block_rows=96)  # 10 full blocks and a partial one


def same(a, b) -> None:
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_rows_and_slices_are_numpys(twin):
    array, rows = twin
    assert len(rows) == 1000 and rows.shape == (1000, 7)
    for i in (0, 95, 96, 97, 500, 999, -1, -1000):
        same(rows[i], array[i])
    for key in (slice(None), slice(90, 200), slice(None, None, 7), slice(990, 2000), slice(300, 100, -3),
                slice(5, 5)):
        same(rows[key], array[key])
    same(rows[10:400, [0, 6, 3]], array[10:400, [0, 6, 3]])
    same(rows, array)
    same(np.stack(list(rows)), array)
    same(np.concatenate([c for _, c in rows.chunks(128)]), array)
    with pytest.raises(IndexError):
        rows[1000]


def test_views_compose_like_numpy_indexing(twin):
    array, rows = twin
    pick = np.array([999, 0, 0, 500, 96, 95])
    same(rows[pick], array[pick])
    mask = np.arange(1000) % 3 == 0
    view = rows[mask]
    assert isinstance(view, ScanRows) and len(view) == mask.sum()
    same(view, array[mask])
    same(view[10:20], array[mask][10:20])
    flipped = view[..., ::-1]
    same(flipped, array[mask][..., ::-1])
    same(flipped[3], array[mask][3, ::-1])
    same(flipped[..., ::-1], array[mask])
    same(flipped[np.array([2, 1])], array[mask][..., ::-1][[2, 1]])
    # anything else numpy takes works on the rows read whole
    finite = np.isfinite(array)
    same(rows[finite], array[finite])
    same(np.isfinite(rows), finite)


def test_a_sequential_pass_reads_each_block_once_and_holds_one(twin):
    array, rows = twin
    source = rows._source
    reads = []
    original = source.block
    source.block = lambda b: reads.append(b) or original(b)
    for i in range(len(rows)):
        rows[i]
    assert reads == list(range(11))
    assert rows.blocks_held == 1
    reads.clear()
    rows[100:300]
    assert reads == [1, 2, 3]


def test_a_spool_refuses_a_row_of_another_width():
    spool = ScanSpool(block_rows=4)
    spool.append(np.zeros(3))
    with pytest.raises(ValueError, match="a row of 4 values in a spool of 3"):
        spool.append(np.zeros(4))


def run_parts(array: np.ndarray, sizes: list[int]):
    laser = Laser(beams=5, range_max=5.0)
    from pipeline.ingest import run_table

    a = 0
    for size in sizes:
        s = slice(a, a + size)
        n = len(array[s])
        yield run_table(CaptureRun("r", np.arange(a, a + n) * 0.1, np.zeros((n, 3)), np.full((n, 3), np.nan),
                                   array[s], [None] * n, [False] * n), laser, "site", first_step=a)
        a += size


def test_an_arrow_run_is_read_a_record_batch_at_a_time_and_equals_its_parquet_twin(tmp_path):
    from pipeline.evaluation.replay import load_run

    rng = np.random.default_rng(1)
    array = rng.uniform(0.1, 4.0, (300, 5)).astype(np.float32)
    tables.write_table_parts(tmp_path / "r.arrow", run_parts(array, [128, 0, 128, 44]), "runs")
    tables.write_table(tmp_path / "p" / "r.parquet", pa.concat_tables(run_parts(array, [300])), "runs")
    lazy, whole = load_run(tmp_path / "r.arrow"), load_run(tmp_path / "p" / "r.parquet")
    assert isinstance(lazy.ranges, ScanRows) and isinstance(whole.ranges, np.ndarray)
    same(lazy.ranges, whole.ranges)
    same(lazy.ranges[250], array[250])
    np.testing.assert_array_equal(lazy.t, whole.t)
    np.testing.assert_array_equal(lazy.odom, whole.odom)
    assert lazy.gt is None and whole.gt is None
    steps = tables.read_table(tmp_path / "r.arrow", "runs").column("step").to_numpy()
    np.testing.assert_array_equal(steps, np.arange(300))  # parts carry on the step count


def test_an_arrow_run_with_a_scan_of_other_beams_names_the_row(tmp_path):
    from pipeline.evaluation.replay import load_run

    tables.write_table_parts(tmp_path / "r.arrow", [*run_parts(np.ones((10, 5), np.float32), [10]),
                                                    *run_parts(np.ones((20, 6), np.float32)[10:], [10])], "runs")
    with pytest.raises(InputError) as err:
        load_run(tmp_path / "r.arrow")
    problem = str(err.value.problems[0])
    assert "r.arrow row 10" in problem and "6 beams where the run's scans have 5" in problem


def test_ipc_rows_of_a_written_table(tmp_path):
    array = (np.arange(60, dtype=np.float32) / 20).reshape(20, 3)  # under range_max: kept as they are
    tables.write_table_parts(tmp_path / "r.arrow", run_parts(array, [7, 7, 6]), "runs")
    rows = ipc_rows(tmp_path / "r.arrow", "ranges", [7, 7, 6], 3)
    same(rows, array)
    same(rows[6:8], array[6:8])
