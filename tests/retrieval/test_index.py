"""First-stage indexes: faiss's against exact search on generated and on the micro site's real descriptors,
IVF-PQ's refinement against exact distances, saved indexes, and build-index / load_database with one."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import IndexParams
from pipeline.errors import InputError
from pipeline.retrieval.index import ExactIndex, FaissIndex, auto_lists, auto_pq_bytes, make_index, pq_bits
from pipeline.retrieval.whitening import l2_normalize

faiss = pytest.importorskip("faiss")


def _vectors(n, d=24, seed=0):
    return l2_normalize(np.random.default_rng(seed).normal(size=(n, d))).astype(np.float32)


def _recall(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.mean([len(set(a) & set(b)) / len(b) for a, b in zip(got, want, strict=True)]))


def test_faiss_flat_agrees_with_exact():
    x, q = _vectors(120), _vectors(5, seed=6)
    np.testing.assert_array_equal(make_index("faiss", x).search(q, 8)[1], ExactIndex(x).search(q, 8)[1])


def test_an_inverted_file_probing_every_cell_is_exact_and_one_cell_is_not():
    x, q = _vectors(400), _vectors(5, seed=7)
    want = ExactIndex(x).search(q, 8)[1]
    every = FaissIndex(x, "ivf_flat", IndexParams(ivf_lists=4, ivf_nprobe=4)).search(q, 8)[1]
    np.testing.assert_array_equal(every, want)
    some = FaissIndex(x, "ivf_flat", IndexParams(ivf_lists=16, ivf_nprobe=1)).search(q, 8)[1]
    assert (some >= -1).all() and not np.array_equal(some, want)


def test_ivf_pq_refinement_returns_exact_distances_in_order():
    x, q = _vectors(2000, d=32), _vectors(6, d=32, seed=8)
    index = FaissIndex(x, "ivf_pq", IndexParams(ivf_lists=8, ivf_nprobe=8, pq_bytes=8, refine=8))
    d, i = index.search(q, 10)
    exact = ((q[:, None, :] - x[i]) ** 2).sum(-1)
    np.testing.assert_allclose(d, exact, rtol=1e-5, atol=1e-6)
    assert np.all(np.diff(d, axis=1) >= 0)
    coarse = FaissIndex(x, "ivf_pq", IndexParams(ivf_lists=8, ivf_nprobe=8, pq_bytes=8, refine=1))
    truth = ExactIndex(x).search(q, 10)[1]
    # 8 bytes for 32 floats lose the order; re-sorting 80 code neighbours by exact distance wins it back
    assert _recall(i, truth) > _recall(coarse.search(q, 10)[1], truth)
    assert _recall(i, truth) >= 0.9


def test_auto_sizes():
    assert auto_pq_bytes(112) == 56 and auto_pq_bytes(24) == 12 and auto_pq_bytes(7) == 1
    assert auto_lists(10**6) == 4000 and auto_lists(100) == 2 and auto_lists(10) == 1
    assert pq_bits(10**6) == 8 and pq_bits(39 * 256) == 8 and pq_bits(39 * 256 - 1) == 7 and pq_bits(156) == 2
    assert pq_bits(10) == 1


def test_pq_bytes_must_divide_the_dimension():
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="does not divide"):
        FaissIndex(_vectors(500), "ivf_pq", IndexParams(ivf_lists=4, pq_bytes=5))


def test_a_saved_index_answers_as_the_built_one_and_refuses_other_vectors(tmp_path):
    x, q = _vectors(800), _vectors(4, seed=9)
    for kind in ("hnsw", "ivf_pq"):
        built = FaissIndex(x, kind, IndexParams(ivf_lists=8, pq_bytes=6))
        built.save(tmp_path / f"{kind}.faiss")
        loaded = FaissIndex.load(tmp_path / f"{kind}.faiss", x, kind, IndexParams(ivf_lists=8, pq_bytes=6))
        np.testing.assert_array_equal(loaded.search(q, 10)[1], built.search(q, 10)[1])
        with pytest.raises(InputError, match="re-run `siteloc build-index`"):
            FaissIndex.load(tmp_path / f"{kind}.faiss", x[:700], kind)


def _real(micro_extraction):
    """The micro site's IPA descriptors, PCA-whitened on the mapping stops as build-index does (raw, a barely
    trained detector's are nearly one vector): the stops as the database, the run frames as queries."""
    from pipeline.io import tables
    from pipeline.retrieval.whitening import PCAWhitening

    ipa = tables.descriptor_matrix(tables.read_table(micro_extraction / "ipa.parquet", "ipa"))
    split = tables.read_table(micro_extraction / "catalog.parquet", "catalog").column("split").to_pylist()
    runs = np.array([s.startswith("run:") for s in split])
    white = PCAWhitening().fit(ipa[~runs])
    return (l2_normalize(white.transform(ipa[~runs])).astype(np.float32),
            l2_normalize(white.transform(ipa[runs])).astype(np.float32))


def test_each_index_finds_the_exact_neighbours_of_real_descriptors(micro_extraction):
    db, queries = _real(micro_extraction)  # 156 stops, 14 frames; 112-d
    assert len(db) >= 100 and len(queries) >= 10
    truth = ExactIndex(db).search(queries, 10)[1]

    def recall(kind, **params):
        return _recall(make_index(kind, db, IndexParams(**params)).search(queries, 10)[1], truth)

    assert recall("hnsw") >= 0.98
    assert recall("ivf_flat", ivf_nprobe=4) == 1.0  # 4 cells (156 // 39), all visited: exact
    assert recall("ivf_flat", ivf_nprobe=1) < 0.9  # one of 4: the neighbours in other cells are missed
    # 2-bit codes (156 training vectors): the codes alone order poorly, re-sorting more of them by exact distance
    # recovers the neighbours
    coarse, default, wide = (recall("ivf_pq", ivf_nprobe=4, refine=r) for r in (1, 4, 8))
    assert coarse < default < wide and wide >= 0.9


def test_build_index_saves_the_approximate_index_and_the_database_loads_it(micro_extraction, tmp_path):
    from pipeline.config import load_config
    from pipeline.io import tables
    from pipeline.retrieval.database import load_database, query_database, run_build_index

    hnsw_cfg = load_config("ci", ["retrieval.index=hnsw"])
    built = run_build_index(hnsw_cfg, inputs={"descriptors": micro_extraction}, outputs={"out": tmp_path / "db"})
    assert (built / "ipa_index.faiss").is_file()
    saved = load_database(built)  # the kind it was built with, read from the file
    assert isinstance(saved.index, FaissIndex) and saved.index.kind == "hnsw"
    exact = load_database(built, index="exact")
    assert isinstance(exact.index, ExactIndex)
    ipa = tables.descriptor_matrix(tables.read_table(micro_extraction / "ipa.parquet", "ipa"))
    for q in ipa[-5:]:
        a, b = query_database(saved, q, None, rerank=False), query_database(exact, q, None, rerank=False)
        np.testing.assert_array_equal(a.first, b.first)
        np.testing.assert_allclose(a.candidates, b.candidates)
