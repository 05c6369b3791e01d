"""Runtime settings of the camera methods against each other, on the same runs, seeds and retrievals.

    .venv/bin/python benchmarks/relocalisation_study.py --bundle bundles/office-0.1.0 \\
        --data data/reference/ingested --variant bundle: \\
        --variant checked:filter.scan_check.pool=50

Each `--variant NAME:KEY=VALUE[,KEY=VALUE...]` replays the site's query runs through the bundle's
Localizer with those filter settings changed (`filter.` keys, as `siteloc export --set` takes them;
nothing after the colon: the bundle's own), for the methods that use the camera (proposed,
image_reloc, sequence; `--methods`), `--trials` seeds each. Every frame is described and retrieved once
for all variants. Printed per variant and method: global localization (converged replays, median
converge step, p90 error before the first kidnapping) and kidnapping recovery (recovered, within 15 /
40 steps, median / p90 steps, within 15 steps and under 10 cm: issue 8's measure) and the mean time of
an update. Replays run in `--workers` processes (the figures do not depend on it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import machine_info  # noqa: E402


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, rest = text.partition(":")
    changes = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.startswith("filter."):
            sys.exit(f"--variant {text}: '{item}' is not filter.KEY=VALUE")
        changes[key[len("filter."):]] = yaml.safe_load(value)
    return name or "bundle", changes


def with_changes(cfg, changes: dict):
    """The filter config with dotted keys changed (validated by the config model)."""
    from pipeline.config import FilterConfig

    raw = cfg.model_dump()
    for key, value in changes.items():
        node = raw
        *path, last = key.split(".")
        for part in path:
            node = node[part]
        if last not in node:
            sys.exit(f"filter.{key}: no such setting")
        node[last] = value
    return FilterConfig.model_validate(raw)


def print_check_cost(loc, run, data: Path) -> None:
    """What the runtime pays per check of retrieved poses against a scan (no cache: as a robot runs it)."""
    import numpy as np

    from pipeline.machine import median_ms
    from pipeline.runtime.scancheck import check_candidates

    t = min(10, len(run) - 1)
    image, scan = data / run.image_ids[t], loc.scan(run.ranges[t])
    pool = loc.retrieved(image)
    sc = loc.filter_config.scan_check
    print("| what | ms (median of 20) |\n|---|---|")
    print(f"| single-image retrieval (detector + Top-50 + RPA) | {median_ms(lambda: loc.retrieved(image), 20):.1f} |")
    for n in (4, 10, 20, 50):
        ms = median_ms(lambda n=n: check_candidates(loc.verifier, loc.map, pool[:n], scan, keep=4,
                                                    samples=sc.samples, std_xy=0.5, std_theta=np.radians(15),
                                                    rng=np.random.default_rng(0), rounds=sc.rounds), 20)
        print(f"| scan check of {n} poses x {sc.samples} samples x {sc.rounds} rounds ({sc.model} model) | {ms:.2f} |")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True, help="the ingested site with query runs")
    ap.add_argument("--variant", action="append", required=True, help="NAME:filter.KEY=VALUE,...")
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--methods", default="proposed,image_reloc,sequence")
    ap.add_argument("--run", action="append", help="only these query runs")
    ap.add_argument("--workers", type=int, default=None, help="replay processes (default: the usable cores; 1: in "
                    "this process). Update times are measured with that many replays sharing the machine")
    ap.add_argument("--slow", type=int, default=None, help="also list the kidnappings recovered later than this "
                    "many steps (or never), per variant and method")
    args = ap.parse_args()
    for text in machine_info():
        print(text)
    from pipeline.evaluation.experiments import query_runs, run_experiments, summarise
    from pipeline.evaluation.report import kidnap_table
    from pipeline.runtime.localizer import Localizer

    loc = Localizer.from_bundle(args.bundle)
    runs = query_runs(args.data, args.run)
    own = loc.filter_config
    variants = [parse_variant(v) for v in args.variant]
    methods = args.methods.split(",")
    print(f"\nbundle {args.bundle}; {len(runs)} query runs x {args.trials} trials\n")
    print_check_cost(loc, runs[0], args.data)
    print("| variant | method | converged | median step | p90 global | recovered | within 15 / 40 | "
          "median / p90 steps | within 15 and 10 cm | mean error, converged | update ms | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    retrieve = None
    for name, changes in variants:
        loc.filter_config = with_changes(own, changes)
        t0 = time.perf_counter()
        results, retrieve = run_experiments(loc, args.data, runs, trials=args.trials, methods=methods,
                                            retrieve=retrieve, progress=False, workers=args.workers)
        wall = time.perf_counter() - t0
        summary = {m: summarise(r) for m, r in results.items()}
        kid = kidnap_table(results, summary)
        for m in results:
            s, k = summary[m], kid.get(m)
            rec = (f"{k['recovered']} / {k['kidnappings']} | {k['within_15']} / {k['within_40']} | "
                   f"{k['steps_median']} / {k['steps_p90']} | {k['within_15_and_10cm']}") if k else "- | - | - | -"
            print(f"| {name} | {m} | {s['converged']} / {s['replays']} | {s['converged_step_median']} | "
                  f"{s['error_p90_global_m']} | {rec} | {s['error_mean_converged_m']} | {s['update_ms_mean']} | "
                  f"{wall:.0f} |", flush=True)
            if args.slow is not None:
                slow = [f"{r.run}@{k} trial {r.trial}: {'never' if v is None else v}"
                        for r in results[m] for k, v in zip(r.kidnaps, r.metrics["recovery_steps"], strict=True)
                        if v is None or v > args.slow]
                print(f"|   slow ({len(slow)}): {'; '.join(slow)} |")
        loc.filter_config = own


if __name__ == "__main__":
    main()
