"""`build-index` a record batch at a time: region offsets, sampled rows and whitened regions read in batches
equal the in-memory computation; a region file of many batches is sliced as one matrix and answers the same
queries."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.io import tables
from pipeline.retrieval import region_stream
from pipeline.retrieval.search import ChunkedRows, region_offsets


def test_chunked_rows_slice_as_the_joined_matrix():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(size=(n, 3)).astype(np.float32) for n in (4, 0, 1, 6, 0, 3)]
    joined, rows = np.vstack(chunks), ChunkedRows(chunks)
    assert rows.shape == joined.shape and len(rows) == 14
    for lo in range(15):
        for hi in range(lo, 16):
            np.testing.assert_array_equal(rows[lo:hi], joined[lo:hi])
    assert np.shares_memory(rows[4:5], chunks[2])  # within one chunk: a view, not a copy
    with pytest.raises(IndexError):
        rows[0:10:2]


def _rpa_file(path, owners, d=5, seed=0):
    m = len(owners)
    desc = np.random.default_rng(seed).normal(size=(m, d)).astype(np.float32)
    ids = [f"i{o:03d}" for o in owners]
    tables.write_table(path, tables.to_table("rpa", {
        "image_id": ids, "region": list(range(m)), "source": ["proposal"] * m, "x1": [0.0] * m, "y1": [0.0] * m,
        "x2": [1.0] * m, "y2": [1.0] * m, "score": [0.5] * m, "class_id": [0] * m,
        "descriptor": tables.descriptor_array(desc)}), "rpa")
    return ids, desc


def test_offsets_and_rows_read_in_batches_equal_the_whole_table(tmp_path, monkeypatch):
    monkeypatch.setattr(region_stream, "BATCH_ROWS", 7)  # many batches, image groups split across them
    counts = np.random.default_rng(1).integers(0, 5, size=30)
    owners = np.repeat(np.arange(30), counts)
    ids, desc = _rpa_file(tmp_path / "rpa.parquet", owners)
    images = [f"i{k:03d}" for k in range(30)]
    offsets = region_stream.region_offsets_streamed(tmp_path / "rpa.parquet", images)
    np.testing.assert_array_equal(offsets, region_offsets(images, ids))
    rows = np.sort(np.random.default_rng(2).choice(len(owners), 17, replace=False))
    np.testing.assert_array_equal(region_stream.read_rows(tmp_path / "rpa.parquet", rows), desc[rows])
    keep = np.zeros(30, bool)
    keep[::3] = True
    parts = list(region_stream.whitened_parts(tmp_path / "rpa.parquet", offsets, keep, lambda x: 2 * x))
    kept = np.flatnonzero(keep[owners])
    np.testing.assert_array_equal(np.vstack([tables.descriptor_matrix(p) for p in parts]), 2 * desc[kept])
    assert sum(p.num_rows for p in parts) == len(kept)


def test_regions_out_of_the_catalogs_order_are_refused_naming_the_file(tmp_path, monkeypatch):
    monkeypatch.setattr(region_stream, "BATCH_ROWS", 3)
    _rpa_file(tmp_path / "rpa.parquet", [0, 0, 1, 0, 2, 2])  # image 0 again after image 1, in the next batch
    with pytest.raises(InputError, match="rpa.parquet.*not grouped"):
        region_stream.region_offsets_streamed(tmp_path / "rpa.parquet", ["i000", "i001", "i002"])
    with pytest.raises(InputError, match="do not list|does not list"):
        region_stream.region_offsets_streamed(tmp_path / "rpa.parquet", ["i000", "i001"])


def test_build_index_in_batches_writes_the_in_memory_database(micro_extraction, micro_site, tmp_path, monkeypatch):
    from pipeline.retrieval.database import load_database, query_database, run_build_index
    from pipeline.retrieval.evaluate import fit_whitenings, load_extracted, split_database_queries, whitened_database

    cfg, _, _ = micro_site
    monkeypatch.setattr(region_stream, "BATCH_ROWS", 500)  # the region file in several record batches
    out = run_build_index(cfg, inputs={"descriptors": micro_extraction}, outputs={"out": tmp_path / "index"})
    # The twin: everything in memory, as build-index did before it streamed.
    ex = load_extracted(micro_extraction)
    db, _ = split_database_queries(ex)
    w_ipa, w_rpa = fit_whitenings(ex, db, cfg.retrieval.whitening, cfg.retrieval)
    twin = whitened_database(ex, db, w_ipa, w_rpa)
    rdb = load_database(out)
    assert isinstance(rdb.db.rpa, ChunkedRows) and len(rdb.db.rpa.chunks) > 1
    assert rdb.db.image_ids == twin.image_ids
    np.testing.assert_array_equal(rdb.db.offsets, twin.offsets)
    np.testing.assert_allclose(rdb.db.ipa, twin.ipa, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rdb.db.rpa[0:len(rdb.db.rpa)], twin.rpa, rtol=0, atol=1e-6)
    for i in split_database_queries(ex)[1][:8]:
        rows = np.arange(ex.offsets[i], ex.offsets[i + 1])[:10]
        got = query_database(rdb, ex.ipa[i], ex.rpa[rows], top_n=20)
        from pipeline.retrieval.search import retrieve

        q = w_ipa.transform(ex.ipa[i][None])[0] if w_ipa is not None else ex.ipa[i]
        reg = w_rpa.transform(ex.rpa[rows]) if w_rpa is not None else ex.rpa[rows]
        want = retrieve(twin, rdb.index, q, reg, top_n=20)
        np.testing.assert_array_equal(got.first, want.first)
        # Whitened a batch at a time, regions differ by < 1e-6: the re-ranking scores agree to that, and the
        # Top-4 is the same but where two scores tie that closely.
        np.testing.assert_allclose(got.region_scores, want.region_scores, rtol=0, atol=1e-5)
        score = dict(zip(want.first.tolist(), want.region_scores.tolist(), strict=True))
        np.testing.assert_allclose([score[k] for k in got.ranked[:4]], [score[k] for k in want.ranked[:4]],
                                   rtol=0, atol=1e-5)


PEAK_SCRIPT = """
import resource, sys
from pathlib import Path
from pipeline.config import load_config
from pipeline.retrieval.database import run_build_index
run_build_index(load_config("ci"), inputs={"descriptors": Path(sys.argv[1])}, outputs={"out": Path(sys.argv[2])})
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def _extraction(root, n: int, per: int = 100, d: int = 128):
    """An extract output of n images with `per` regions each, written a row group per 64 images as extract does."""
    from pipeline.retrieval.whitening import l2_normalize

    rng = np.random.default_rng(0)
    root.mkdir()
    ids = [f"img{k:05d}.jpg" for k in range(n)]
    tables.write_table(root / "catalog.parquet", tables.to_table("catalog", {
        "image_id": ids, "x": rng.uniform(0, 50, n).tolist(), "y": rng.uniform(0, 50, n).tolist(),
        "theta": rng.uniform(-3, 3, n).tolist(), "group": ids, "split": ["train"] * (n - 100) + ["test"] * 100}),
        "catalog")
    tables.write_table(root / "ipa.parquet", tables.to_table("ipa", {
        "image_id": ids, "descriptor": tables.descriptor_array(l2_normalize(rng.normal(size=(n, d))))}), "ipa")

    def parts():
        for k in range(0, n, 64):
            m = min(64, n - k) * per
            yield tables.to_table("rpa", {
                "image_id": [ids[k + j // per] for j in range(m)], "region": [j % per for j in range(m)],
                "source": ["proposal"] * m, "x1": [0.0] * m, "y1": [0.0] * m, "x2": [1.0] * m, "y2": [1.0] * m,
                "score": [0.5] * m, "class_id": [0] * m,
                "descriptor": tables.descriptor_array(l2_normalize(rng.normal(size=(m, d))).astype(np.float32))})

    tables.write_table_parts(root / "rpa.parquet", parts(), "rpa")
    return root, n * per * d * 4 / 1e6


def test_build_index_memory_does_not_grow_with_the_regions(tmp_path):
    """Twice the regions (77 -> 154 MB): build-index's peak memory stays put (when it held the regions, twice
    over, it grew by more than they did). The RPA whitening's sample is capped (100 000 rows) in both."""
    import subprocess
    import sys

    peaks, sizes = [], []
    for n in (1500, 3000):
        x, mb = _extraction(tmp_path / f"x{n}", n)
        proc = subprocess.run([sys.executable, "-c", PEAK_SCRIPT, str(x), str(tmp_path / f"index{n}")],
                              capture_output=True, text=True, check=True)
        peaks.append(int(proc.stdout.strip().splitlines()[-1]) / 1024)
        sizes.append(mb)
    grown, more = peaks[1] - peaks[0], sizes[1] - sizes[0]
    assert grown < 0.5 * more, f"peak memory {peaks[0]:.0f} -> {peaks[1]:.0f} MB for {more:.0f} MB more regions"
