"""How many iterations `train-detector --init-from` needs to reach a from-scratch detector's mAP.

    .venv/bin/python benchmarks/detector_init_from.py --old-model DET --data NEW_SITE --work DIR
        [--scratch-iterations 300] [--init-iterations 25,50,100,200] [--config demo]

DET is the detector of the site before the change (a `train-detector` output), NEW_SITE the updated site
database (`siteloc update`'s output; `benchmarks/update_workflow.py` leaves both in its --work folder:
det/ and v2-upd/). A detector is trained on NEW_SITE from the configured weights for --scratch-iterations,
and from DET for each of --init-iterations; each is scored with `evaluate-detector` (COCO mAP@0.5 on the
held-out stops), as is the old model untouched. Prints the machine, a table of iterations, seconds and
mAP, and the first fine-tune that reaches the from-scratch mAP, with its share of the from-scratch time.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old-model", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--scratch-iterations", type=int, default=300)
    ap.add_argument("--init-iterations", default="25,50,100,200")
    ap.add_argument("--config", default="demo")
    args = ap.parse_args()

    from pipeline.config import load_config
    from pipeline.detection.evaluate import run_evaluate_detector
    from pipeline.detection.train import run_train_detector
    from pipeline.machine import machine_summary

    print(json.dumps(machine_summary()))
    shutil.rmtree(args.work, ignore_errors=True)
    runs = [("from scratch", args.scratch_iterations, None)]
    runs += [("--init-from", int(n), args.old_model) for n in args.init_iterations.split(",")]
    rows = []
    ev = run_evaluate_detector(load_config(args.config), inputs={"model": args.old_model, "data": args.data},
                               outputs={"out": args.work / "old-model-eval"})
    old_map = json.loads((ev / "metrics.json").read_text())["map_50"]
    print(f"  the old model as it is: mAP@0.5 {old_map:.3f}", flush=True)
    for label, n, init in runs:
        cfg = load_config(args.config, [f"detector.iterations={n}", f"detector.checkpoint_every={n}",
                                        f"detector.warmup_iterations={min(100, n // 4)}"])
        out = args.work / f"{label.strip('-').replace(' ', '_')}-{n}"
        t = time.perf_counter()
        model = run_train_detector(cfg, inputs={"data": args.data, **({"init_from": init} if init else {})},
                                   outputs={"out": out}, progress=False)
        seconds = time.perf_counter() - t
        ev = run_evaluate_detector(cfg, inputs={"model": model, "data": args.data}, outputs={"out": out / "eval"})
        m = json.loads((ev / "metrics.json").read_text())
        rows.append((label, n, seconds, m["map_50"]))
        print(f"  {label} {n} it: {seconds:.1f} s, mAP@0.5 {m['map_50']:.3f}", flush=True)
    print("\n| start | iterations | training s | mAP@0.5 |\n| --- | --- | --- | --- |")
    print(f"| the old model, not trained | 0 | 0 | {old_map:.3f} |")
    for label, n, seconds, m in rows:
        print(f"| {label} | {n} | {seconds:.1f} | {m:.3f} |")
    scratch = rows[0]
    reached = next((r for r in rows[1:] if r[3] >= scratch[3]), None)
    if reached:
        print(f"--init-from reaches the from-scratch mAP ({scratch[3]:.3f}) at {reached[1]} iterations, "
              f"{reached[2] / scratch[2]:.0%} of the from-scratch training time")
    else:
        print(f"no fine-tune reached the from-scratch mAP ({scratch[3]:.3f}); the best: "
              f"{max(r[3] for r in rows[1:]):.3f}")


if __name__ == "__main__":
    main()
