"""Time retrieval: descriptor extraction, query latency with and without re-ranking, and search scaling.

    .venv/bin/python benchmarks/retrieval.py [--model DIR] [--device auto] [--dim 112] [--max-db 1000000]

1. Extraction (when --model gives a trained detector): images/s of `describe` (one detector pass,
   IPA + RPA of 100 proposals) on random 640 x 480 images, batch 1 and 4.
2. Query latency on a synthetic database of 10 000 images with 100 regions each (`--dim`-d unit
   descriptors): IPA Top-50 alone, and Top-50 + RPA re-ranking with 10 query regions.
3. First-stage search time per query against database size, 1e3 .. `--max-db` synthetic descriptors:
   numpy exact search vs faiss IndexFlatL2 (exact) vs two approximate faiss indexes, HNSW (M 32, up to
   `--hnsw-max`: its graph takes long to build) and IVF-Flat (4 sqrt(N) cells, 16 probed), with their
   recall@50 against exact search and build times; batches of 16 queries.
Prints the machine first, and faiss's speed as a ratio to numpy's in the same run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.config import IndexParams  # noqa: E402
from pipeline.machine import machine_info  # noqa: E402
from pipeline.retrieval.index import make_index  # noqa: E402
from pipeline.retrieval.search import Database, ExactIndex, retrieve  # noqa: E402
from pipeline.retrieval.whitening import l2_normalize  # noqa: E402


def _timed(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats


def extraction(model: Path, device: str) -> None:
    import torch

    from pipeline.detection.inference import load_detector
    from pipeline.retrieval.extract import describe

    det = load_detector(model, device=device)
    gen = torch.Generator().manual_seed(0)
    images = [torch.rand(3, 480, 640, generator=gen) for _ in range(8)]
    for batch in (1, 4):
        t = _timed(lambda b=batch: [describe(det, images[i:i + b], 100, 0.3) for i in range(0, 8, b)], 1)
        print(f"extraction ({det.config['builder']['backbone']}, {det.device}), 640x480, batch {batch}: "
              f"{8 / t:.2f} img/s")


def query_latency(dim: int) -> None:
    rng = np.random.default_rng(0)
    n, regions = 10_000, 100
    db = Database([str(i) for i in range(n)], rng.uniform(0, 50, (n, 3)), l2_normalize(rng.normal(size=(n, dim))),
                  l2_normalize(rng.normal(size=(n * regions, dim))), np.arange(0, n * regions + 1, regions))
    index = ExactIndex(db.ipa)
    q, qr = l2_normalize(rng.normal(size=dim)), l2_normalize(rng.normal(size=(10, dim)))
    plain = _timed(lambda: retrieve(db, index, q, None, top_n=50), 50)
    full = _timed(lambda: retrieve(db, index, q, qr, top_n=50), 50)
    print(f"query on {n} images x {regions} regions, {dim}-d: IPA Top-50 {plain * 1e3:.2f} ms, "
          f"+ RPA re-ranking (10 query regions) {full * 1e3:.2f} ms (x{full / plain:.1f})")


def scaling(dim: int, max_db: int, hnsw_max: int) -> None:
    try:
        import faiss  # noqa: F401

        have_faiss = True
    except ImportError:
        have_faiss = False
        print("faiss not installed: numpy only (pip install faiss-cpu)")
    rng = np.random.default_rng(1)
    queries = l2_normalize(rng.normal(size=(16, dim)))
    print(f"\nfirst-stage search, ms per query (batches of 16), {dim}-d, Top-50:")
    print(f"{'database':>10} {'numpy exact':>12} {'faiss flat':>11} {'ratio':>6} {'hnsw':>8} {'recall':>6} "
          f"{'build s':>7} {'ivf':>8} {'recall':>6} {'build s':>7}")
    n = 1000
    while n <= max_db:
        x = l2_normalize(rng.normal(size=(n, dim)).astype(np.float32))
        exact = ExactIndex(x)
        t_np = _timed(lambda e=exact: e.search(queries, 50), 3) / len(queries)
        row = f"{n:>10} {t_np * 1e3:>12.3f}"
        if have_faiss:
            flat = make_index("faiss", x)
            t_flat = _timed(lambda f=flat: f.search(queries, 50), 3) / len(queries)
            row += f" {t_flat * 1e3:>11.3f} {t_np / t_flat:>6.2f}"
            truth = exact.search(queries, 50)[1]
            approximate = {"hnsw": IndexParams(hnsw_m=32, hnsw_ef_search=64) if n <= hnsw_max else None,
                           "ivf_flat": IndexParams(ivf_lists=int(4 * np.sqrt(n)), ivf_nprobe=16)}
            for kind, params in approximate.items():
                if params is None:
                    row += f" {'-':>8} {'-':>6} {'-':>7}"
                    continue
                t0 = time.perf_counter()
                index = make_index(kind, x, params)
                build = time.perf_counter() - t0
                t_a = _timed(lambda a=index: a.search(queries, 50), 3) / len(queries)
                got = index.search(queries, 50)[1]
                recall = np.mean([len(set(a) & set(b)) / 50 for a, b in zip(truth, got, strict=True)])
                row += f" {t_a * 1e3:>8.3f} {recall:>6.3f} {build:>7.1f}"
        print(row, flush=True)
        n *= 10


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, help="a trained detector (output of siteloc train-detector)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--dim", type=int, default=112, help="descriptor dimension (112: EfficientNet-Lite0; 512: VGG16)")
    ap.add_argument("--max-db", type=int, default=1_000_000)
    ap.add_argument("--hnsw-max", type=int, default=100_000, help="largest database given an HNSW graph")
    args = ap.parse_args()
    for line in machine_info():
        print(line)
    print()
    if args.model:
        extraction(args.model, args.device)
    query_latency(args.dim)
    scaling(args.dim, args.max_db, args.hnsw_max)


if __name__ == "__main__":
    main()
