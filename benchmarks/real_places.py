"""Retrieval on real photographs: `evaluate-places` on the shared real indoor sets (and any other place set).

    .venv/bin/python benchmarks/real_places.py [--data ../shared/data/real-images] [--work /tmp/siteloc-places]
        [--extra PLACES ...] [--backbone lite0_s16 lite0_s32] [--scales 1 1/2] [--threads 1]

Writes a place_set.yaml for each shared set into --work (the images stay where they are: `root` points at
them): RTAB-Map's corridors (images 1-40 the database, 41-84 the queries, samples_GT.bmp the matches) and
VPR-Bench's corridor (ref / query, query i matching ref i-2..i+2). --extra adds place sets or ingested sites
(an office floor: `siteloc ingest` of `siteloc synth`). Each set is measured with every backbone, pooling
(sum, gem), whitening (none, pca, shrinkage) and scale set (with --detector, each one-scale variant also
re-ranked by RPA), torch on --threads threads (the robot's figure is
one core). Prints the machine, then per set the Markdown table of `evaluate-places` and, per whitening, the
change of R@1 against no whitening over all sets, backbones and poolings (the "cannot hurt" check).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SETS = {
    "rtabmap-corridors": {"root": "rtabmap-corridors", "images": ".", "database": "1-40", "queries": "41-84",
                          "positives": {"matrix": "samples_GT.bmp"}},
    "vpr-bench-corridor": {"root": "vpr-bench-corridor", "database": "ref", "queries": "query",
                           "positives": {"aligned": 2}},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "real-images")
    ap.add_argument("--work", type=Path, default=Path("/tmp/siteloc-places"))
    ap.add_argument("--extra", type=Path, nargs="*", default=[])
    ap.add_argument("--backbone", nargs="+", default=["lite0_s16", "lite0_s32"])
    ap.add_argument("--scales", nargs="+", default=["1", "1/2"])
    ap.add_argument("--max-side", type=int, default=640)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--detector", type=Path, default=None,
                    help="a train-detector output: also re-rank each one-scale variant by RPA")
    ap.add_argument("--pooling", nargs="+", default=None)
    ap.add_argument("--whitening", nargs="+", default=None)
    args = ap.parse_args()

    import torch
    import yaml

    from pipeline.config import load_config
    from pipeline.machine import machine_summary
    from pipeline.retrieval.place_eval import POOLINGS, WHITENINGS, run_evaluate_places

    torch.set_num_threads(args.threads)
    print(f"machine: {machine_summary()}; torch threads {torch.get_num_threads()}; "
          f"{time.strftime('%Y-%m-%d')}", flush=True)
    sets = []
    for name, spec in SETS.items():
        folder = args.work / "sets" / name
        folder.mkdir(parents=True, exist_ok=True)
        spec = {**spec, "name": name, "root": str((args.data / spec["root"]).resolve())}
        (folder / "place_set.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
        sets.append(folder)
    sets += list(args.extra)
    scales = [tuple(float(v) for v in s.split("/")) for s in args.scales]
    docs = []
    for places in sets:
        t0 = time.perf_counter()
        out = run_evaluate_places(load_config("demo"), inputs={"places": places, "detector": args.detector},
                                  outputs={"out": args.work / "out" / Path(places).name}, backbones=args.backbone,
                                  poolings=args.pooling or list(POOLINGS),
                                  whitenings=args.whitening or list(WHITENINGS), scales=scales,
                                  max_side=args.max_side, force=True, progress=sys.stderr.isatty())
        print(f"\n({time.perf_counter() - t0:.0f} s)\n")
        print((out / "report.md").read_text(), flush=True)
        docs.append(json.loads((out / "metrics.json").read_text()))
    print("### Whitening against none (R@1, every set x backbone x pooling x scales)\n")
    print("| whitening | better | same | worse | mean change | worst change |")
    print("| --- | --- | --- | --- | --- | --- |")
    for wh in [w for w in (args.whitening or WHITENINGS) if w != "none"]:
        diffs = []
        for doc in docs:
            by = {(v["backbone"], v["pooling"], tuple(v["scales"]), v["whitening"], v["rerank"]): v["recall@1"]
                  for v in doc["variants"]}
            diffs += [r - by[(b, p, s, "none", rr)] for (b, p, s, w, rr), r in by.items()
                      if w == wh and (b, p, s, "none", rr) in by]
        if not diffs:
            continue
        better = sum(d > 1e-9 for d in diffs)
        worse = sum(d < -1e-9 for d in diffs)
        print(f"| {wh} | {better} | {len(diffs) - better - worse} | {worse} | {sum(diffs) / len(diffs):+.3f} | "
              f"{min(diffs):+.3f} |")


if __name__ == "__main__":
    main()
