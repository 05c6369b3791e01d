"""First-stage search at 10^4-10^6 database images, on real descriptors: latency, recall@50, build time, memory.

    .venv/bin/python benchmarks/scale.py --descriptors EXTRACTION [EXTRACTION ...] [--sizes 10000 100000 1000000]
        [--replicate jitter|rotate] [--kinds exact hnsw ivf_flat ivf_pq] [--queries 200] [--set KEY=VALUE]

EXTRACTION: outputs of `siteloc extract` (one per reference floor, e.g. `synth` with different seeds).
Their mapping-stop IPA descriptors, PCA-whitened on those stops as `build-index` does, are the real
database; their run frames are the queries. To reach a size, the database is replicated (the copies are
told apart from the originals in the printout):

- `jitter`: each copy of a view is that view's descriptor plus isotropic noise as large as the median
  distance between a view and its nearest other view (re-normalised): a denser building, the query's
  Top-50 a crowd of near-duplicates (hard for an approximate index);
- `rotate`: each copy of the whole database turned by a random orthogonal matrix: other buildings with the
  same descriptor statistics (their views are distractors, the neighbourhoods keep their real shape).

For each size and index kind (`retrieval.index_params` with --set overrides): build seconds, index bytes
per image (faiss's serialised size), ms per query (one query at a time, as the runtime asks, and a batch
of 16), recall@50 against exact search, and up to --rerank-max images the whole query (`search.retrieve`:
first stage + RPA re-ranking of the Top-50 with the query's 10 regions) on regions memory-mapped from a
file, as `load_database` maps database_rpa.arrow, with the Top-50's regions read one after the other and
asked for all at once first (`Database.paged`, `search.will_need`: what the runtime does). The file was
just written: a warm page cache where it fits in memory, disk reads where it does not (10^6 images: 45 GB);
--cold unmaps the file and drops the page cache before each kind's measure (needs root).
Prints the machine first; each kind's speed as a ratio to exact.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import machine_info  # noqa: E402


class Real:
    """The extractions' descriptors, whitened on their database views as build-index does: IPA of the database
    views and of the queries; regions of each (offsets into the region matrices), queries' ordered as a query's
    are matched (detections first, at most `query_regions`)."""

    def __init__(self, paths: list[Path], query_regions: int = 10):
        from pipeline.io import tables
        from pipeline.retrieval.search import query_region_order, region_offsets
        from pipeline.retrieval.whitening import PCAWhitening, l2_normalize

        ipa_db, ipa_q, rpa_db, rpa_q, off_db, off_q = [], [], [], [], [0], [0]
        for path in paths:
            ipa = tables.descriptor_matrix(tables.read_table(path / "ipa.parquet", "ipa"))
            ids = tables.read_table(path / "ipa.parquet", "ipa").column("image_id").to_pylist()
            split = tables.read_table(path / "catalog.parquet", "catalog").column("split").to_pylist()
            rpa_t = tables.read_table(path / "rpa.parquet", "rpa")
            rpa = tables.descriptor_matrix(rpa_t)
            offsets = region_offsets(ids, rpa_t.column("image_id").to_pylist())
            sources, scores = rpa_t.column("source").to_numpy(zero_copy_only=False), rpa_t.column("score").to_numpy()
            for k, s in enumerate(split):
                lo, hi = offsets[k], offsets[k + 1]
                if s.startswith("run:"):
                    ipa_q.append(ipa[k])
                    rpa_q.append(rpa[lo:hi][query_region_order(sources[lo:hi], scores[lo:hi], query_regions)])
                    off_q.append(off_q[-1] + len(rpa_q[-1]))
                else:
                    ipa_db.append(ipa[k])
                    rpa_db.append(rpa[lo:hi])
                    off_db.append(off_db[-1] + hi - lo)
        w_ipa, w_rpa = PCAWhitening().fit(np.array(ipa_db)), PCAWhitening().fit(np.vstack(rpa_db))
        self.db = l2_normalize(w_ipa.transform(np.array(ipa_db))).astype(np.float32)
        self.queries = l2_normalize(w_ipa.transform(np.array(ipa_q))).astype(np.float32)
        self.db_regions = l2_normalize(w_rpa.transform(np.vstack(rpa_db))).astype(np.float32)
        self.query_regions = l2_normalize(w_rpa.transform(np.vstack(rpa_q))).astype(np.float32)
        self.db_offsets, self.query_offsets = np.array(off_db), np.array(off_q)


def nearest_other_distance(x: np.ndarray) -> float:
    """Median over views of the distance to the nearest other view (exact)."""
    from pipeline.retrieval.index import ExactIndex

    d, _ = ExactIndex(x).search(x, 2)
    return float(np.median(np.sqrt(np.maximum(d[:, 1], 0.0))))


class Copies:
    """Copy c of the real set (c = 1, 2, ...): `jitter` adds isotropic noise as large as the median distance
    between a view and its nearest other view; `rotate` turns it by a Haar-random orthogonal matrix."""

    def __init__(self, real: np.ndarray, how: str, seed: int):
        self.how, self.seed, self.dim = how, seed, real.shape[1]
        self.sigma = nearest_other_distance(real) / np.sqrt(self.dim) if how == "jitter" else 0.0

    def __call__(self, x: np.ndarray, c: int, salt: int = 0) -> np.ndarray:
        from pipeline.retrieval.whitening import l2_normalize

        rng = np.random.default_rng([self.seed, c, salt])
        if self.how == "jitter":
            y = x + rng.normal(scale=self.sigma, size=x.shape).astype(np.float32)
        else:
            q, r = np.linalg.qr(np.random.default_rng([self.seed, c]).normal(size=(x.shape[1], x.shape[1])))
            y = x @ (q * np.sign(np.diag(r))).astype(np.float32)
        return l2_normalize(y).astype(np.float32)


def replicate(x: np.ndarray, n: int, copies: Copies) -> np.ndarray:
    """n vectors: x first, then its copies until n."""
    out = np.empty((n, x.shape[1]), dtype=np.float32)
    for c, k in enumerate(range(0, n, len(x))):
        take = min(len(x), n - k)
        out[k:k + take] = x[:take] if c == 0 else copies(x[:take], c)
    return out


def replicate_regions(real: Real, n: int, copies: Copies, path: Path):
    """The regions of n database images (image j: those of real view j mod n_real, copied as its IPA is) in a
    memory-mapped float32 file, as database_rpa.arrow is mapped; returns (matrix, offsets)."""
    n_real = len(real.db)
    counts = np.diff(real.db_offsets)
    per_image = np.resize(counts, n)
    offsets = np.concatenate([[0], np.cumsum(per_image)])
    shape = (int(offsets[-1]), real.db_regions.shape[1])
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=shape)
    for c, k in enumerate(range(0, n, n_real)):
        take = min(n_real, n - k)
        src = real.db_regions[: real.db_offsets[take]]
        out[offsets[k]:offsets[k] + len(src)] = src if c == 0 else copies(src, c, salt=1)
    out.flush()
    del out
    return np.load(path, mmap_mode="r"), offsets


def timed_queries(index, queries: np.ndarray, k: int) -> tuple[float, float]:
    """(ms per query asked one at a time, ms per query in batches of 16)."""
    index.search(queries[:1], k)
    t0 = time.perf_counter()
    for q in queries:
        index.search(q[None], k)
    single = (time.perf_counter() - t0) / len(queries) * 1e3
    t0 = time.perf_counter()
    for b in range(0, len(queries), 16):
        index.search(queries[b:b + 16], k)
    return single, (time.perf_counter() - t0) / len(queries) * 1e3


def index_bytes(index) -> int | None:
    """Serialised size of a faiss index (None for numpy's exact search: the vectors themselves)."""
    import faiss

    if not hasattr(index, "index"):
        return None
    return int(faiss.serialize_index(index.index).nbytes)


def drop_page_cache() -> None:
    import os

    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("1\n")
    except OSError as exc:
        sys.exit(f"--cold: cannot drop the page cache ({exc}); run as root, or leave --cold out")


def whole_query_ms(db, index, real: Real, picks: np.ndarray, top_n: int) -> tuple[float, float]:
    """ms per query of `search.retrieve` (first stage + RPA re-ranking of the Top-N), one query at a time:
    (reading the Top-N's regions one after the other, asking for all their pages first as a paged database does).
    The two alternate query by query, so both meet the page cache in the same state."""
    from pipeline.retrieval.search import retrieve

    def run(i, paged):
        db.paged = paged
        lo, hi = real.query_offsets[i], real.query_offsets[i + 1]
        retrieve(db, index, real.queries[i], real.query_regions[lo:hi], top_n=top_n)

    run(picks[0], True)
    spent = {False: 0.0, True: 0.0}
    for k, i in enumerate(picks):
        t0 = time.perf_counter()
        run(i, bool(k % 2))
        spent[bool(k % 2)] += time.perf_counter() - t0
    return spent[False] / len(picks[::2]) * 1e3, spent[True] / len(picks[1::2]) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--descriptors", type=Path, nargs="+", required=True, help="`siteloc extract` outputs")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--replicate", choices=("jitter", "rotate"), default="jitter")
    ap.add_argument("--kinds", nargs="+", default=["exact", "hnsw", "ivf_flat", "ivf_pq"])
    ap.add_argument("--queries", type=int, default=200,
                    help="query frames, drawn at random (seeded) from every extraction's run frames")
    ap.add_argument("--k", type=int, default=50, help="Top-k compared with exact search (the paper's Top-50)")
    ap.add_argument("--rerank-max", type=int, default=100_000,
                    help="largest size given a region file, for the whole query's time (about 45 kB an image)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/siteloc-scale"), help="where region files go")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="retrieval.index_params overrides, e.g. --set ivf_nprobe=64")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cold", action="store_true",
                    help="drop the OS page cache before each whole-query measure (needs root): every region read "
                         "comes from the disk, as on a server that has not answered those places yet")
    args = ap.parse_args()
    from pipeline.config import IndexParams
    from pipeline.retrieval.index import ExactIndex, make_index
    from pipeline.retrieval.search import Database

    print("\n".join(machine_info()))
    overrides = dict(s.split("=", 1) for s in args.set)
    params = IndexParams(**{k: (None if v == "null" else int(v)) for k, v in overrides.items()})
    print(f"index params: {params.model_dump()}")
    real = Real(args.descriptors)
    picks = np.random.default_rng(args.seed).permutation(len(real.queries))[:args.queries]
    queries = real.queries[picks]
    print(f"real: {len(real.db)} database views ({len(real.db_regions)} regions), {len(real.queries)} query frames "
          f"({len(picks)} used), IPA {real.db.shape[1]}-d, RPA {real.db_regions.shape[1]}-d (whitened); "
          f"replicated by {args.replicate}")
    copies = Copies(real.db, args.replicate, args.seed + 1)
    print("\n| images | index | build (s) | bytes / image | ms / query (one) | ms / query (batch 16) | "
          "speed vs exact (one) | recall@50 | whole query, regions read in turn (ms) | "
          "whole query, pages asked for at once (ms) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    args.work.mkdir(parents=True, exist_ok=True)
    for n in args.sizes:
        x = replicate(real.db, n, copies)
        db = None
        if n <= args.rerank_max:
            regions, offsets = replicate_regions(real, n, copies, args.work / f"regions-{n}.npy")
            db = Database([str(i) for i in range(n)], np.zeros((n, 3)), x, regions, offsets)
        exact = ExactIndex(x)
        truth = exact.search(queries, args.k)[1]
        base = None
        for kind in args.kinds:
            t0 = time.perf_counter()
            index = exact if kind == "exact" else make_index(kind, x, params)
            build = time.perf_counter() - t0 if kind != "exact" else 0.0
            single, batch = timed_queries(index, queries, args.k)
            base = single if kind == "exact" else base
            got = index.search(queries, args.k)[1]
            recall = np.mean([len(set(a) & set(b)) / args.k for a, b in zip(got, truth, strict=True)])
            size = index_bytes(index) if kind != "exact" else x.nbytes
            ratio = f"{base / single:.1f}x" if base else "-"
            if db is not None and args.cold:  # unmapped first: the OS keeps the pages a process maps
                db.rpa = regions = None
                drop_page_cache()
                db.rpa = regions = np.load(args.work / f"regions-{n}.npy", mmap_mode="r")
            whole = " | ".join(f"{ms:.2f}" for ms in whole_query_ms(db, index, real, picks, args.k)) \
                if db is not None else "- | -"
            print(f"| {n} | {kind} | {build:.1f} | {size / n:.0f} | {single:.3f} | {batch:.3f} | {ratio} | "
                  f"{recall:.3f} | {whole} |", flush=True)
            del index
        if db is not None:
            del db, regions
            (args.work / f"regions-{n}.npy").unlink()


if __name__ == "__main__":
    main()
