"""What seed 001's area prior costs per camera image, and how its ball tree scales, on this machine.

    .venv/bin/python benchmarks/prior_query.py --bundle bundles/office-0.1.0 --data data/reference/ingested
    .venv/bin/python benchmarks/prior_query.py --scaling-only

With a bundle exported with --prior: the multi-layer encoder (ONNX, as the runtime runs it), the prior's
query (compression + ball tree k=10 + scoring of three layers) for each measure, and beside them the
single-image retrieval of seed 000 (ONNX detector + IPA Top-50 + RPA re-ranking) on the same frames.
Then, on synthetic 128-d vectors (clustered, as compressed CNN features are): k=10 search time of
scikit-learn's BallTree against brute-force numpy (the peer), and the tree's build time, for database
sizes 1e3-1e6 (`--max-n`). Medians of `--repeat` runs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import machine_info, median_ms  # noqa: E402


def bundle_costs(bundle: Path, data: Path, repeat: int) -> None:
    from pipeline.evaluation.experiments import query_runs
    from pipeline.prior.model import MEASURES
    from pipeline.runtime.localizer import Localizer

    loc = Localizer.from_bundle(bundle)
    if loc.area_prior is None:
        sys.exit(f"{bundle}: no area prior; export it with --prior")
    run = query_runs(data, None)[0]
    frame = data / next(i for i in run.image_ids if i)
    ap = loc.area_prior
    layers = ap.layers(frame)
    prior = ap.prior
    print(f"\nbundle {bundle}: {len(prior.labels)} images, {len(prior.classes)} classes, layers "
          + ", ".join(f"{n} {prior.vectors[n].shape[1]}-d" for n in prior.layers))
    print("| what (one camera image) | ms |\n|---|---|")
    print(f"| multi-layer encoder (ONNX) | {median_ms(lambda: ap.layers(frame), repeat):.1f} |")
    for m in MEASURES:
        prior.probabilities(layers, measure=m)  # trees and caches built
        print(f"| prior query, {m} | {median_ms(lambda m=m: prior.probabilities(layers, measure=m), repeat):.2f} |")
    print(f"| seed 000 retrieval (detector + Top-50 + RPA), the peer | "
          f"{median_ms(lambda: loc.candidates(frame), repeat):.1f} |")


def scaling(max_n: int, repeat: int, seed: int = 0) -> None:
    from sklearn.neighbors import BallTree

    rng = np.random.default_rng(seed)
    print("\n| database (128-d) | BallTree build (s) | BallTree k=10 (ms) | brute force k=10 (ms) | ratio |")
    print("|---|---|---|---|---|")
    n = 1000
    while n <= max_n:
        centres = rng.standard_normal((max(n // 20, 1), 128)).astype(np.float32)
        db = centres[rng.integers(0, len(centres), n)] + 0.3 * rng.standard_normal((n, 128)).astype(np.float32)
        q = db[rng.integers(0, n, 8)] + 0.3 * rng.standard_normal((8, 128)).astype(np.float32)
        t0 = time.perf_counter()
        tree = BallTree(db, leaf_size=40)
        build = time.perf_counter() - t0
        sq = (db**2).sum(axis=1)

        def brute(db=db, q=q, sq=sq):
            d = sq - 2.0 * db @ q[0]
            return np.argpartition(d, 10)[:10]

        tree_ms = median_ms(lambda tree=tree, q=q: tree.query(q[:1], k=10), repeat)
        brute_ms = median_ms(brute, repeat)
        print(f"| {n:.0e} | {build:.2f} | {tree_ms:.2f} | {brute_ms:.2f} | {brute_ms / tree_ms:.1f}x |")
        n *= 10


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, help="a bundle exported with --prior")
    ap.add_argument("--data", type=Path, help="the ingested site (a query run's frame)")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--max-n", type=int, default=1_000_000)
    ap.add_argument("--scaling-only", action="store_true")
    args = ap.parse_args()
    for text in machine_info():
        print(text)
    if not args.scaling_only:
        if args.bundle is None or args.data is None:
            sys.exit("--bundle and --data are needed (or --scaling-only)")
        bundle_costs(args.bundle, args.data, args.repeat)
    scaling(args.max_n, args.repeat)


if __name__ == "__main__":
    main()
