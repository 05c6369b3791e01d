"""The filter on large, sparse, fast logs: tracking and global localization, honestly counted.

    .venv/bin/python benchmarks/sparse_logs.py --work /tmp/sparse [--logs campus intel-corrected ...]
        [--global-trials 10] [--tracking-trials 3] [--every-m 1.0] [--set filter.KEY=VALUE ...]

The logs: the campus of `siteloc synth-laser` (270 x 240 m at 5 cm, a scan every 0.9 m, 40 m range,
odometry drifting tens of metres) and the five CARMEN logs of ../shared/data/carmen/ ingested with
`ingest-log --every-m 1` (one scan per metre; maps from every scan). Each is made under --work once and
reused. For each log: tracking from the true first pose (--tracking-trials seeds) and global localization
from a uniform start (--global-trials seeds), with the `demo` config and any --set overrides. Prints the
machine and a Markdown table: converged (settled under 0.5 m and never lost track), lost track (with
the steps), median first-convergence step, share of steps within 0.5 m after convergence, median error
after convergence and over all steps, evo's APE rmse, ms per update. docs/results.md
quotes it.
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

CARMEN = REPO.parent / "shared" / "data" / "carmen"
LOGS = ["campus", "intel-corrected", "aces-corrected", "csail-corrected", "fhw-corrected", "freiburg-079-corrected"]


def dataset(work: Path, log: str, every_m: float) -> Path:
    """The ingested (or generated) dataset of `log` under `work`, made once."""
    from pipeline.config import load_config

    out = work / ("campus" if log == "campus" else f"{log}-every{every_m:g}m")
    if (out / "map.yaml").is_file():
        return out
    if log == "campus":
        from pipeline.sitegen.synth_laser import load_laser_preset, run_synth_laser

        return run_synth_laser(load_laser_preset("campus"), outputs={"out": out}, progress=False)
    from pipeline.ingest_log import run_ingest_log

    cfg = load_config("demo")
    cfg = cfg.model_copy(update={"ingest_log": cfg.ingest_log.model_copy(update={"scan_every_m": every_m})})
    return run_ingest_log(cfg, inputs={"log": CARMEN / f"{log}.log.gz"}, outputs={"out": out}, progress=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--logs", nargs="*", default=LOGS)
    ap.add_argument("--every-m", type=float, default=1.0)
    ap.add_argument("--tracking-trials", type=int, default=3)
    ap.add_argument("--global-trials", type=int, default=10)
    ap.add_argument("--config", default="demo")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    from pipeline.config import load_config
    from pipeline.localize import run_localize

    print("\n".join(machine_info()))
    cfg = load_config(args.config, args.set)
    print("overrides: " + (", ".join(args.set) or "none"))
    rows = []
    for log in args.logs:
        data = dataset(args.work, log, args.every_m)
        steps = json.loads((data / "report.json").read_text())["scans"]
        for mode, init, trials in (("tracking", "pose", args.tracking_trials), ("global", "uniform",
                                                                                  args.global_trials)):
            t0 = time.perf_counter()
            out = run_localize(cfg, inputs={"data": data}, outputs={"out": args.work / "runs" / log / mode},
                               init=init, trials=trials, force=True, progress=False)
            s = next(iter(json.loads((out / "metrics.json").read_text())["summary"].values()))
            rows.append((log, steps, mode, s))
            print(f"{log:24s} {mode:9s} {json.dumps(s)}  ({time.perf_counter() - t0:.0f} s)", flush=True)

    def f(v, fmt="{:.3f}"):
        return "-" if v is None else fmt.format(v)

    print("\n| log | steps | mode | converged | lost track (steps) | median conv. step | within 0.5 m after conv. | "
          "median error after conv. (m) | median error, all (m) | APE rmse, evo (m) | ms / update |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for log, steps, mode, s in rows:
        lost = "; ".join(",".join(map(str, x)) for x in s["lost_track_steps"] if x)
        print(f"| {log.removesuffix('-corrected')} | {steps} | {mode} | {s['converged']}/{s['trials']} | "
              f"{s['lost_track']}" + (f" ({lost})" if lost else "") + " | "
              f"{f(s['converged_step_median'], '{:.0f}')} | {f(s['within_threshold_share_median'], '{:.0%}')} | "
              f"{f(s['error_median_m'])} | {f(s['error_median_all_m'])} | {f(s['ape_rmse_m_median'], '{:.2f}')} | "
              f"{f(s['update_ms_mean'], '{:.1f}')} |")


if __name__ == "__main__":
    main()
