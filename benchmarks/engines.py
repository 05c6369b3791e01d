"""Throughput of the image stages on the local pool and on Ray, at 1 and at all usable cores.

    .venv/bin/python benchmarks/engines.py --model models/detector --data data/reference/ingested
                                           [--stages extract frame-features prior-features] [--repeat 2]

Each variant runs the whole stage (`run_extract`, `run_frame_features`, `run_prior_features`, a fresh
output each time) in its own process, so that the core count is the process's affinity mask and Ray's
workers start from nothing:

- local, N cores: the default engine, pinned to N cores (its pool fills them: N onnxruntime sessions);
- ray, N workers: `--engine ray` on a local Ray of N CPUs (N actors), started before the clock starts (as a
  cluster is, for `--ray-address`); the start of that Ray is printed apart.

Prints the machine, each variant's images per second (best of `--repeat`) and Ray's as a ratio to the local
pool's at the same core count, in the same run. Both engines export and check the graphs first (a few
seconds, counted in both). The outputs are compared too: Ray's tables must equal the local ones.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

STAGES = ("extract", "frame-features", "prior-features")


def run_variant(stage: str, engine: str, cores: int, model: Path | None, data: Path, out: Path,
                sets: list[str]) -> dict:
    """In this process: pin to `cores`, start Ray if asked, run the stage; seconds and images."""
    os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:cores]))
    from pipeline.config import load_config

    cfg = load_config("demo", sets)
    ray_start = None
    if engine == "ray":
        from pipeline.ray_engine import connect

        t0 = time.perf_counter()
        connect(None, num_cpus=cores)
        ray_start = time.perf_counter() - t0
    t0 = time.perf_counter()
    if stage == "extract":
        from pipeline.retrieval.extract import run_extract

        path = run_extract(cfg, inputs={"model": model, "data": data}, outputs={"out": out}, progress=False,
                           executor=engine)
        images = json.loads((path / "report.json").read_text())["images"]
    elif stage == "frame-features":
        from pipeline.sequence.frames import run_frame_features

        path = run_frame_features(cfg, inputs={"data": data}, outputs={"out": out}, progress=False, executor=engine)
        images = json.loads((path / "report.json").read_text())["frames"]
    else:
        from pipeline.prior.features import run_prior_features

        path = run_prior_features(cfg, inputs={"data": data}, outputs={"out": out}, progress=False, executor=engine)
        images = json.loads((path / "report.json").read_text())["images"]
    return {"seconds": time.perf_counter() - t0, "images": images, "ray_start_s": ray_start}


def same_outputs(a: Path, b: Path) -> bool:
    """Every Parquet table of the two outputs holds the same rows (descriptors bit for bit)."""
    import pyarrow.parquet as pq

    names = sorted(p.name for p in a.glob("*.parquet"))
    return names == sorted(p.name for p in b.glob("*.parquet")) and all(
        pq.read_table(a / n).equals(pq.read_table(b / n)) for n in names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, help="a train-detector output (for extract)")
    ap.add_argument("--data", type=Path, required=True, help="an ingested site")
    ap.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES))
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides (demo)")
    ap.add_argument("--variant", nargs=4, metavar=("STAGE", "ENGINE", "CORES", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.variant:
        stage, engine, cores, out = args.variant
        print(json.dumps(run_variant(stage, engine, int(cores), args.model, args.data, Path(out), args.set)))
        return
    if "extract" in args.stages and args.model is None:
        ap.error("--model is needed for extract")
    from pipeline.machine import machine_info, usable_core_count

    for line in machine_info():
        print(line)
    all_cores = usable_core_count()
    core_counts = sorted({1, all_cores})
    rows = []
    with tempfile.TemporaryDirectory(prefix="siteloc-engines-") as tmp:
        for stage in args.stages:
            best: dict[tuple[str, int], dict] = {}
            for rep in range(args.repeat):
                for cores in core_counts:
                    for engine in ("local", "ray"):
                        out = Path(tmp) / f"{stage}-{engine}-{cores}-{rep}"
                        cmd = [sys.executable, __file__, "--data", str(args.data), "--variant", stage, engine,
                               str(cores), str(out), *(["--model", str(args.model)] if args.model else []),
                               *sum((["--set", s] for s in args.set), [])]
                        proc = subprocess.run(cmd, capture_output=True, text=True)
                        if proc.returncode != 0:
                            sys.exit(f"{stage} {engine} {cores}: failed\n{proc.stderr[-3000:]}")
                        r = json.loads(proc.stdout.strip().splitlines()[-1])
                        r["out"] = out
                        key = (engine, cores)
                        if key not in best or r["seconds"] < best[key]["seconds"]:
                            best[key] = r
            for cores in core_counts:
                local, ray = best[("local", cores)], best[("ray", cores)]
                rows.append((stage, cores, local, ray, same_outputs(local["out"], ray["out"])))
    print(f"\nbest of {args.repeat}; images per second of the whole stage (graph export and checks included)\n")
    print(f"{'stage':<15} {'cores':>5} {'images':>7} {'local img/s':>12} {'ray img/s':>10} {'ray/local':>10} "
          f"{'ray start s':>12} {'same output':>12}")
    for stage, cores, local, ray, same in rows:
        lr, rr = local["images"] / local["seconds"], ray["images"] / ray["seconds"]
        print(f"{stage:<15} {cores:>5} {local['images']:>7} {lr:>12.1f} {rr:>10.1f} {rr / lr:>10.2f} "
              f"{ray['ray_start_s']:>12.1f} {str(same):>12}")


if __name__ == "__main__":
    main()
