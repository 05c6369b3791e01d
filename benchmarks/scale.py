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
of 16), recall@50 against exact search. Prints the machine first; each kind's speed as a ratio to exact.
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


def real_descriptors(paths: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """(database, queries) float32, whitened on the database views of every extraction together."""
    from pipeline.io import tables
    from pipeline.retrieval.whitening import PCAWhitening, l2_normalize

    db, q = [], []
    for path in paths:
        ipa = tables.descriptor_matrix(tables.read_table(path / "ipa.parquet", "ipa"))
        split = tables.read_table(path / "catalog.parquet", "catalog").column("split").to_pylist()
        runs = np.array([s.startswith("run:") for s in split])
        db.append(ipa[~runs])
        q.append(ipa[runs])
    db, q = np.vstack(db), np.vstack(q)
    white = PCAWhitening().fit(db)
    return (l2_normalize(white.transform(db)).astype(np.float32), l2_normalize(white.transform(q)).astype(np.float32))


def nearest_other_distance(x: np.ndarray) -> float:
    """Median over views of the distance to the nearest other view (exact, in blocks)."""
    from pipeline.retrieval.index import ExactIndex

    d, _ = ExactIndex(x).search(x, 2)
    return float(np.median(np.sqrt(np.maximum(d[:, 1], 0.0))))


def replicate(x: np.ndarray, n: int, how: str, rng: np.random.Generator) -> np.ndarray:
    """n vectors: x first, then copies made by `how` (see the module) until n."""
    from pipeline.retrieval.whitening import l2_normalize

    out = np.empty((n, x.shape[1]), dtype=np.float32)
    k = min(n, len(x))
    out[:k] = x[:k]
    sigma = nearest_other_distance(x) / np.sqrt(x.shape[1]) if how == "jitter" else 0.0
    while k < n:
        take = min(len(x), n - k)
        if how == "jitter":
            copy = x[:take] + rng.normal(scale=sigma, size=(take, x.shape[1])).astype(np.float32)
        else:
            q, r = np.linalg.qr(rng.normal(size=(x.shape[1], x.shape[1])))
            copy = x[:take] @ (q * np.sign(np.diag(r))).astype(np.float32)  # Haar-random orthogonal
        out[k:k + take] = l2_normalize(copy).astype(np.float32)
        k += take
    return out


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--descriptors", type=Path, nargs="+", required=True, help="`siteloc extract` outputs")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--replicate", choices=("jitter", "rotate"), default="jitter")
    ap.add_argument("--kinds", nargs="+", default=["exact", "hnsw", "ivf_flat", "ivf_pq"])
    ap.add_argument("--queries", type=int, default=200,
                    help="query frames, drawn at random (seeded) from every extraction's run frames")
    ap.add_argument("--k", type=int, default=50, help="Top-k compared with exact search (the paper's Top-50)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="retrieval.index_params overrides, e.g. --set ivf_nprobe=64")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from pipeline.config import IndexParams
    from pipeline.retrieval.index import ExactIndex, make_index

    print("\n".join(machine_info()))
    overrides = dict(s.split("=", 1) for s in args.set)
    params = IndexParams(**{k: (None if v == "null" else int(v)) for k, v in overrides.items()})
    print(f"index params: {params.model_dump()}")
    real, queries = real_descriptors(args.descriptors)
    rng = np.random.default_rng(args.seed)
    queries = queries[rng.permutation(len(queries))[:args.queries]]
    print(f"real: {len(real)} database views, {len(queries)} queries, {real.shape[1]}-d (whitened); "
          f"replicated by {args.replicate}")
    print("\n| images | index | build (s) | bytes / image | ms / query (one) | ms / query (batch 16) | "
          "speed vs exact (one) | recall@50 |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for n in args.sizes:
        x = replicate(real, n, args.replicate, np.random.default_rng(args.seed + 1))
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
            print(f"| {n} | {kind} | {build:.1f} | {size / n:.0f} | {single:.3f} | {batch:.3f} | {ratio} | "
                  f"{recall:.3f} |", flush=True)
            del index


if __name__ == "__main__":
    main()
