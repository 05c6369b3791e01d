"""The retrieval database on disk: the memory-mapped region table answers as the in-RAM one and stays out of
the process's own memory; region offsets by Arrow against the Python twin."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest

from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.retrieval.database import load_database, query_database, region_offsets_of
from pipeline.retrieval.search import region_offsets
from pipeline.retrieval.whitening import l2_normalize


def _write_database(root, n=60, regions=(3, 9), d=16, rpa_file="database_rpa.arrow", seed=0):
    rng = np.random.default_rng(seed)
    counts = rng.integers(*regions, size=n)
    ids = [f"img{k:04d}.jpg" for k in range(n)]
    owner = np.repeat(np.arange(n), counts)
    m = len(owner)
    root.mkdir(parents=True)
    tables.write_table(root / "database_ipa.parquet", tables.to_table("ipa", {
        "image_id": ids, "descriptor": tables.descriptor_array(l2_normalize(rng.normal(size=(n, d))))}), "ipa")
    tables.write_table(root / rpa_file, tables.to_table("rpa", {
        "image_id": [ids[o] for o in owner], "region": list(range(m)), "source": ["proposal"] * m,
        "x1": [0.0] * m, "y1": [0.0] * m, "x2": [1.0] * m, "y2": [1.0] * m, "score": [0.5] * m,
        "class_id": [0] * m, "descriptor": tables.descriptor_array(l2_normalize(rng.normal(size=(m, d))))}), "rpa")
    tables.write_table(root / "catalog.parquet", tables.to_table("catalog", {
        "image_id": ids, "x": rng.uniform(0, 30, n).tolist(), "y": rng.uniform(0, 30, n).tolist(),
        "theta": rng.uniform(-3, 3, n).tolist(), "group": ids, "split": ["train"] * n}), "catalog")
    (root / "report.json").write_text(json.dumps({"whitening": "none"}))
    return ids, owner


def test_the_memory_mapped_regions_answer_as_the_parquet_ones(tmp_path):
    _write_database(tmp_path / "arrow")
    _write_database(tmp_path / "parquet", rpa_file="database_rpa.parquet")
    mapped, in_ram = load_database(tmp_path / "arrow"), load_database(tmp_path / "parquet")
    assert not mapped.db.rpa.flags.owndata and not mapped.db.rpa.flags.writeable  # a view on the file
    np.testing.assert_array_equal(mapped.db.rpa, in_ram.db.rpa)
    np.testing.assert_array_equal(mapped.db.offsets, in_ram.db.offsets)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q, regions = l2_normalize(rng.normal(size=16)), l2_normalize(rng.normal(size=(4, 16)))
        a, b = query_database(mapped, q, regions, top_n=20), query_database(in_ram, q, regions, top_n=20)
        np.testing.assert_array_equal(a.ranked, b.ranked)
        np.testing.assert_array_equal(a.candidates, b.candidates)


def _anon_kb() -> int:
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("RssAnon"))


def test_loading_a_large_database_does_not_read_its_regions_into_memory(tmp_path):
    _write_database(tmp_path / "warm", n=10)
    load_database(tmp_path / "warm")  # imports and first-use allocations out of the measure
    _write_database(tmp_path / "big", n=2000, regions=(90, 110), d=128)  # 200 000 regions: 102 MB of floats
    size_kb = (tmp_path / "big" / "database_rpa.arrow").stat().st_size / 1024
    before = _anon_kb()
    rdb = load_database(tmp_path / "big")
    grown = _anon_kb() - before
    assert rdb.db.rpa.nbytes > 100e6
    assert grown < 0.2 * size_kb, f"{grown} kB of private memory for a {size_kb:.0f} kB region file"


def test_region_offsets_by_arrow_match_the_python_twin_and_refuse_disorder():
    ids = ["a", "b", "c", "d"]
    regions = ["a", "a", "c", "c", "c", "d"]
    got = region_offsets_of(pa.chunked_array([ids]), pa.chunked_array([regions[:3], regions[3:]]))
    np.testing.assert_array_equal(got, region_offsets(ids, regions))
    np.testing.assert_array_equal(got, [0, 2, 2, 5, 6])
    with pytest.raises(ValueError, match="grouped"):
        region_offsets_of(pa.array(ids), pa.array(["a", "c", "a"]))
    with pytest.raises(ValueError, match="unknown"):
        region_offsets_of(pa.array(ids), pa.array(["a", "z"]))


def test_a_database_whose_regions_are_out_of_order_is_refused_naming_the_file(tmp_path):
    ids, _ = _write_database(tmp_path / "db", n=5)
    t = tables.read_table(tmp_path / "db" / "database_rpa.arrow", "rpa")
    tables.write_table(tmp_path / "db" / "database_rpa.arrow", t.take(np.arange(t.num_rows)[::-1].copy()), "rpa")
    with pytest.raises(InputError, match="database_rpa.arrow does not follow"):
        load_database(tmp_path / "db")


def test_a_paged_database_reads_its_regions_concurrently_with_the_same_answer(tmp_path):
    _write_database(tmp_path / "arrow")
    _write_database(tmp_path / "parquet", rpa_file="database_rpa.parquet")
    mapped = load_database(tmp_path / "arrow")
    assert mapped.db.paged and not load_database(tmp_path / "parquet").db.paged
    rng = np.random.default_rng(2)
    for _ in range(5):
        q, regions = l2_normalize(rng.normal(size=16)), l2_normalize(rng.normal(size=(4, 16)))
        mapped.db.paged = True
        a = query_database(mapped, q, regions, top_n=30)
        mapped.db.paged = False
        b = query_database(mapped, q, regions, top_n=30)
        np.testing.assert_array_equal(a.region_scores, b.region_scores)
        np.testing.assert_array_equal(a.ranked, b.ranked)


def test_will_need_advises_each_mapped_range(tmp_path):
    import sys

    from pipeline.retrieval.search import will_need

    _write_database(tmp_path / "arrow", n=50)
    db = load_database(tmp_path / "arrow").db
    views = [db.regions(i) for i in range(50)]
    taken = will_need(views)
    if sys.platform.startswith("linux"):
        assert taken == sum(v.nbytes > 0 for v in views) == 50
    assert will_need([np.zeros((0, 16), np.float32)]) == 0
