"""What image-sequence re-localization costs the runtime, per camera frame and per query, from a bundle.

    .venv/bin/python benchmarks/sequence_runtime.py --bundle bundles/office-0.1.0 --data data/reference/ingested

Times (onnxruntime on this machine's CPU, as the robot runs it): the frame encoder (camera image ->
1000 logits, paid for each frame a sequence query reads, i.e. while re-localizing), the sequence query (LSTM over
the buffered frames + whitening + exact search of the sequence database) at lengths 1-10, and beside
them the single-image retrieval every re-localization already pays (ONNX detector + IPA Top-50 + RPA
re-ranking). Median of `--repeat` runs over frames of the first query run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import machine_info, median_ms  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, required=True, help="a bundle exported with --sequence")
    ap.add_argument("--data", type=Path, required=True, help="the ingested site (its query runs' frames)")
    ap.add_argument("--repeat", type=int, default=10)
    args = ap.parse_args()
    for text in machine_info():
        print(text)
    from pipeline.evaluation.experiments import query_runs
    from pipeline.runtime.localizer import Localizer

    loc = Localizer.from_bundle(args.bundle)
    if loc.sequence is None:
        sys.exit(f"{args.bundle}: no sequence model; export it with --sequence")
    run = query_runs(args.data, None)[0]
    frames = [args.data / i for i in run.image_ids[:10]]
    seq = loc.sequence
    print(f"\nbundle {args.bundle}, {len(seq.db)} sequence windows, {seq.db.shape[1]}-d; frames of {run.name}")
    print("| what | ms |\n|---|---|")
    print(f"| single-image retrieval (detector + Top-50 + RPA) | "
          f"{median_ms(lambda: loc.candidates(frames[0]), args.repeat):.1f} |")
    print(f"| frame encoder (a frame) | {median_ms(lambda: seq.encode(frames[0]), args.repeat):.1f} |")
    logits = np.stack([seq.encode(f) for f in frames])
    for n in range(1, 11):  # the LSTM takes any length; the ring buffer holds `length` (6)

        def query(n=n):
            q = seq.describe(logits[-n:])
            return np.argsort(-(seq.db @ q), kind="stable")[:4]

        print(f"| sequence query, {n} frames | {median_ms(query, args.repeat):.2f} |")

if __name__ == "__main__":
    main()
