"""Localization on the real CARMEN logs: tracking, global localization over seeds, kidnap recovery.

    .venv/bin/python benchmarks/localization_real_logs.py [--data data/carmen] [--out data/localize]
        [--global-trials 10] [--kidnap-trials 5] [--logs intel-corrected aces-corrected ...] [--set KEY=VALUE]
        [--modes tracking global kidnap kidnap+candidates]

Needs the logs ingested first (`siteloc ingest-log` or `make demo`, which writes data/carmen/<log>/).
For every log it runs `siteloc localize`'s library function three ways with the `demo` config:
tracking from the first pose (1 trial), global localization from a uniform start (--global-trials seeds),
and two teleport kidnappings per replay (--kidnap-trials seeds), once recovering with the filter alone
(global restart when lost) and once with simulated retrieval candidates at every step (the runtime's
camera path). Prints the machine and a Markdown table (docs/results.md quotes it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.localize import run_localize  # noqa: E402

LOGS = ["intel-corrected", "aces-corrected", "csail-corrected", "fhw-corrected", "freiburg-079-corrected"]


MODES = ("tracking", "global", "kidnap", "kidnap+candidates")


def kidnap_steps(n_steps: int) -> list[int]:
    return [n_steps // 3, (2 * n_steps) // 3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO / "data" / "carmen")
    ap.add_argument("--out", type=Path, default=REPO / "data" / "localize")
    ap.add_argument("--logs", nargs="*", default=LOGS)
    ap.add_argument("--global-trials", type=int, default=10)
    ap.add_argument("--kidnap-trials", type=int, default=5)
    ap.add_argument("--modes", nargs="*", default=list(MODES), choices=MODES, help="which replays (default: all)")
    ap.add_argument("--config", default="demo")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, as the CLI's --set (e.g. filter.sensor.beam_skip=false)")
    args = ap.parse_args()
    print("\n".join(machine_info()))
    cfg = load_config(args.config, args.set)
    if args.set:
        print("overrides: " + ", ".join(args.set))
    rows = []
    for log in args.logs:
        data = args.data / log
        if not (data / "map.yaml").is_file():
            print(f"skip {log}: {data} has no map.yaml (run siteloc ingest-log first)")
            continue
        n_steps = json.loads((data / "report.json").read_text())["scans"]
        modes = [("tracking", "pose", 1, None), ("global", "uniform", args.global_trials, None),
                 ("kidnap", "pose", args.kidnap_trials, kidnap_steps(n_steps)),
                 ("kidnap+candidates", "candidates", args.kidnap_trials, kidnap_steps(n_steps))]
        for mode, init, trials, kid in modes:
            if mode not in args.modes:
                continue
            t0 = time.perf_counter()
            out = run_localize(cfg, inputs={"data": data}, outputs={"out": args.out / log / mode}, init=init,
                               trials=trials, kidnap_at=kid, force=True, progress=False)
            s = json.loads((out / "metrics.json").read_text())["summary"][log]
            rows.append((log, mode, s, time.perf_counter() - t0))
            print(f"{log:24s} {mode:18s} {json.dumps(s)}  ({time.perf_counter() - t0:.0f} s)", flush=True)

    def fmt(v, f="{:.3f}"):
        return "-" if v is None else f.format(v)

    print("\n| log | mode | converged | lost track | median conv. step | within 0.5 m after conv. | "
          "median error after conv. (m) | median error, all steps (m) | kidnaps recovered | median recovery steps "
          "| ms / update |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for log, mode, s, _ in rows:
        kid = f"{s['recovered']}/{s['kidnaps']}" if s["kidnaps"] else "-"
        lost = f"{s['lost_track']} (" + "; ".join(",".join(map(str, x)) for x in s["lost_track_steps"] if x) + ")" \
            if s["lost_track"] else "0"
        print(f"| {log.removesuffix('-corrected')} | {mode} | {s['converged']}/{s['trials']} | {lost} | "
              f"{fmt(s['converged_step_median'], '{:.0f}')} | {fmt(s['within_threshold_share_median'], '{:.0%}')} | "
              f"{fmt(s['error_median_m'])} | {fmt(s['error_median_all_m'])} | {kid} | "
              f"{fmt(s['recovery_steps_median'], '{:.0f}')} | {fmt(s['update_ms_mean'], '{:.1f}')} |")


if __name__ == "__main__":
    main()
