"""How well quality without ground truth (pipeline/runtime/quality.py) tells right estimates from wrong ones.

    .venv/bin/python benchmarks/beam_agreement.py [--work /tmp/siteloc-quality] [--seeds 10] [--max-steps 2000]
        [--kidnap-at 0.5] [--logs intel aces ...] [--no-synth] [--tolerances 0.05 0.1 0.15 0.2 0.3]

Replays with ground truth, through `siteloc localize`'s library function with a uniform start (global
localization) over `--seeds` seeds, so that there are early wrong steps (the search) and later right ones, and
one teleport kidnapping per replay at `--kidnap-at` of its steps (a filter confidently tracking a wrong pose:
the case a spread cannot see). Sources: the five CARMEN logs, ingested with `ingest-log`'s library function
into --work (once) and cut to their first --max-steps scans, and a small synthetic campus (`synth-laser`,
120 x 100 m, a 600 m drive, parked cars the map lacks). A step is right when its error is under 0.5 m,
wrong over 2 m (between: left out). Per source: right and wrong steps, ROC AUC of the beam agreement and of
the (negated) spread, the threshold of best balanced accuracy, the steps misclassified at the defaults of
`QualityRule`, and the same for the whole rule (agreement, spread, tracking). Then per replay: `assess`
against the ground truth's verdict (metrics.json `held`). Prints the machine and Markdown tables.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.io import tables  # noqa: E402
from pipeline.io.map_yaml import read_map  # noqa: E402
from pipeline.runtime.grid import LaserMap  # noqa: E402
from pipeline.runtime.quality import QualityRule, assess, beam_agreement, spread_m  # noqa: E402

LOGS = ["intel", "aces", "csail", "fhw", "freiburg-079"]
RIGHT_M, WRONG_M = 0.5, 2.0
#: The campus preset shrunk to 120 x 100 m, its parked cars in proportion (6 of 25).
SYNTH = {"size": [120.0, 100.0], "blocks": [2, 2], "route_length": 600.0, "parked_cars": 6}


def ingest(work: Path, carmen: Path, cfg, logs: list[str]) -> dict[str, Path]:
    """Each log's dataset directory in `work`, ingested with `ingest-log`'s library function when missing."""
    from pipeline.ingest_log import run_ingest_log

    out = {}
    for name in logs:
        data = work / "carmen" / f"{name}-corrected"
        if not (data / "map.yaml").is_file():
            run_ingest_log(cfg, inputs={"log": carmen / f"{name}-corrected.log.gz"}, outputs={"out": data},
                           force=True, progress=False)
        out[name] = data
    return out


def synth(work: Path) -> Path:
    from pipeline.sitegen.synth_laser import load_laser_preset, run_synth_laser

    data = work / "synth"
    if not (data / "map.yaml").is_file():
        run_synth_laser(load_laser_preset("campus", SYNTH), outputs={"out": data}, force=True, progress=False)
    return data


def cut(data: Path, dest: Path, max_steps: int) -> Path:
    """A copy of the dataset whose runs keep their first `max_steps` steps (the map is shared)."""
    if dest.exists():
        shutil.rmtree(dest)
    (dest / "runs").mkdir(parents=True)
    for f in ("map.yaml", "map.pgm", "site.yaml"):
        if (data / f).is_file():
            shutil.copy(data / f, dest / f)
    for run in sorted((data / "runs").glob("*.parquet")):
        table = tables.read_table(run, "runs")
        tables.write_table(dest / "runs" / run.name, table.slice(0, max_steps), "runs")
    return dest


def signals(data: Path, out: Path, cfg, kidnap_at: list[int] | None, tolerances: list[float],
            truth_tolerance: float) -> list[dict]:
    """Per replay (run, trial): error, agreement per tolerance (and at the true pose), spread, states,
    kidnapped, metrics' `held`."""
    from pipeline.evaluation.replay import load_run, teleport
    from pipeline.localize import _mount

    lmap = LaserMap.from_occupancy(read_map(data / "map.yaml"), cfg.filter.sensor.max_distance)
    est = tables.read_table(out / "estimates.parquet", "estimates").to_pydict()
    metrics = json.loads((out / "metrics.json").read_text())["runs"]
    col = {k: np.asarray(v) for k, v in est.items() if k != "state"}
    states = np.asarray(est["state"])
    runs = {p.stem: load_run(p) for p in (data / "runs").glob("*.parquet")}
    replays = []
    for m_run, trials in metrics.items():
        for m in trials:
            t = m["trial"]
            sel = (col["run"] == m_run) & (col["trial"] == t)
            run = runs[m_run]
            if kidnap_at:  # as run_localize made it: the scans the filter saw
                run = teleport(run, kidnap_at, 10.0, seed=cfg.filter.seed + 1000 * t)
            poses = np.column_stack([col["x"][sel], col["y"][sel], col["theta"][sel]])
            t0 = time.perf_counter()
            agree = {tol: beam_agreement(lmap, poses, run.ranges, run.angle_min, run.angle_increment, run.range_max,
                                         base_from_laser=_mount(data), tolerance_m=tol,
                                         range_min=cfg.filter.sensor.range_min) for tol in tolerances}
            ms = (time.perf_counter() - t0) * 1000.0 / len(tolerances)
            at_truth = beam_agreement(lmap, run.gt, run.ranges, run.angle_min, run.angle_increment, run.range_max,
                                      base_from_laser=_mount(data), tolerance_m=truth_tolerance,
                                      range_min=cfg.filter.sensor.range_min)
            replays.append({"run": m_run, "trial": t, "error": col["error_xy"][sel].astype(np.float64),
                            "error_theta": col["error_theta"][sel].astype(np.float64),
                            "agreement": agree, "at_truth": at_truth,
                            "spread": spread_m(col["cov_xx"][sel], col["cov_xy"][sel], col["cov_yy"][sel]),
                            "states": states[sel].tolist(), "kidnapped": col["kidnapped"][sel].astype(bool),
                            "updated": col["updated"][sel].astype(bool),
                            "held": bool(m["held"]), "gt_converged_step": m["converged_step"],
                            "gt_lost": m["lost_track_steps"], "ms": ms, "beams": run.ranges.shape[1]})
    return replays


def separation(score: np.ndarray, right: np.ndarray, default: float) -> dict:
    """ROC AUC of `score` (higher: right), its threshold of best balanced accuracy, misclassified at `default`."""
    from sklearn.metrics import roc_auc_score, roc_curve

    ok = np.isfinite(score)
    score, right = score[ok], right[ok]
    if right.all() or not right.any():
        return {"auc": None, "best": None, "best_bacc": None, "rw": None, "wr": None, "n_right": int(right.sum()),
                "n_wrong": int((~right).sum())}
    fpr, tpr, thr = roc_curve(right, score)
    bacc = 0.5 * (tpr + 1.0 - fpr)
    k = int(np.argmax(bacc[1:]) + 1)  # thr[0] is +inf
    called = score >= default
    return {"auc": float(roc_auc_score(right, score)), "best": float(thr[k]), "best_bacc": float(bacc[k]),
            "rw": int((right & ~called).sum()), "wr": int((~right & called).sum()), "n_right": int(right.sum()),
            "n_wrong": int((~right).sum())}


def fmt_sep(s: dict, sign: float = 1.0) -> str:
    if s["auc"] is None:
        return "- | - | - | -"
    return (f"{s['auc']:.3f} | {sign * s['best']:.2f} ({s['best_bacc']:.3f}) | "
            f"{s['rw']} ({s['rw'] / s['n_right']:.1%}) | {s['wr']} ({s['wr'] / s['n_wrong']:.1%})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/siteloc-quality"))
    ap.add_argument("--carmen-dir", type=Path, default=REPO.parent / "shared" / "data" / "carmen")
    ap.add_argument("--logs", nargs="*", default=LOGS)
    ap.add_argument("--no-synth", action="store_true", help="leave out the synthetic campus")
    ap.add_argument("--seeds", type=int, default=10, help="uniform-start replays (trials) per source")
    ap.add_argument("--max-steps", type=int, default=2000, help="replay each run's first this many steps")
    ap.add_argument("--kidnap-at", type=float, nargs="*", default=[0.5],
                    help="kidnappings, as fractions of the replayed steps (none: leave out)")
    ap.add_argument("--tolerances", type=float, nargs="*", default=[0.05, 0.1, 0.15, 0.2, 0.3])
    ap.add_argument("--config", default="demo")
    args = ap.parse_args()
    rule = QualityRule()
    if rule.tolerance_m not in args.tolerances:
        args.tolerances = sorted([*args.tolerances, rule.tolerance_m])
    print("\n".join(machine_info()))
    print(f"rule: {rule}; right < {RIGHT_M} m, wrong > {WRONG_M} m; {args.seeds} seeds, uniform start, "
          f"first {args.max_steps} steps, kidnapped at {args.kidnap_at} of them\n", flush=True)
    cfg = load_config(args.config)
    from pipeline.evaluation.replay import load_run
    from pipeline.localize import run_localize

    t_all = time.perf_counter()
    sources = ingest(args.work, args.carmen_dir, cfg, args.logs)
    if not args.no_synth:
        sources["synth"] = synth(args.work)
    replays: dict[str, list[dict]] = {}
    for name, data in sources.items():
        t0 = time.perf_counter()
        short = cut(data, args.work / "cut" / name, args.max_steps)
        n = min(len(load_run(p)) for p in (short / "runs").glob("*.parquet"))
        kid = sorted({int(f * n) for f in args.kidnap_at if 0 < int(f * n) < n}) or None
        out = run_localize(cfg, inputs={"data": short}, outputs={"out": args.work / "localize" / name},
                           init="uniform", trials=args.seeds, kidnap_at=kid, force=True, progress=False)
        replays[name] = signals(short, out, cfg, kid, args.tolerances, rule.tolerance_m)
        ms = np.mean([r["ms"] / len(r["error"]) for r in replays[name]])
        print(f"{name}: {len(replays[name])} replays of {n} steps, kidnapped at {kid}, "
              f"{time.perf_counter() - t0:.0f} s; beam_agreement {ms:.3f} ms per step "
              f"({replays[name][0]['beams']} beams)", flush=True)

    groups = {**replays, "all": [r for rs in replays.values() for r in rs]}
    carmen = [r for name, rs in replays.items() if name != "synth" for r in rs]
    tol = rule.tolerance_m

    print(f"\nTolerance: ROC AUC of the beam agreement (right < {RIGHT_M} m against wrong > {WRONG_M} m)\n")
    print("| source | " + " | ".join(f"{t:g} m" for t in args.tolerances) + " |")
    print("| --- |" + " --- |" * len(args.tolerances))
    for name, rs in groups.items():
        err, _ = labelled(rs)
        keep = (err < RIGHT_M) | (err > WRONG_M)
        aucs = [separation(np.concatenate([r["agreement"][t] for r in rs])[keep], err[keep] < RIGHT_M, 0.5)["auc"]
                for t in args.tolerances]
        print(f"| {name} | " + " | ".join("-" if a is None else f"{a:.3f}" for a in aucs) + " |")

    print(f"\nPer step, tolerance {tol:g} m: ROC AUC, the threshold of best balanced accuracy (that accuracy), and "
          f"misclassified at the defaults (agreement >= {rule.agreement:g}, spread <= {rule.spread_m:g} m; rule: "
          "both and tracking): right called wrong (share of right), wrong called right (share of wrong); the last "
          "column: of the right steps the rule calls wrong, those whose heading is off by more than 10 deg\n")
    print("| source | right steps | wrong steps | agreement AUC | agreement best thr. (bal. acc.) | "
          "agreement: right called wrong | agreement: wrong called right | spread AUC | spread best thr. "
          "(bal. acc.) | spread: right called wrong | spread: wrong called right | rule: right called wrong | "
          "rule: wrong called right | heading off |")
    print("| --- " * 14 + "|")
    for name, rs in groups.items():
        err, keep = labelled(rs)
        right = err[keep] < RIGHT_M
        a = separation(np.concatenate([r["agreement"][tol] for r in rs])[keep], right, rule.agreement)
        s = separation(-np.concatenate([r["spread"] for r in rs])[keep], right, -rule.spread_m)
        e = judge(rs, rule)
        turned = int((e["rw_mask"] & (np.concatenate([r["error_theta"] for r in rs])[keep] > np.radians(10))).sum())
        print(f"| {name} | {a['n_right']} | {a['n_wrong']} | {fmt_sep(a)} | {fmt_sep(s, -1.0)} | "
              f"{e['rw']} ({e['rw'] / max(e['n_right'], 1):.1%}) | {e['wr']} ({e['wr'] / max(e['n_wrong'], 1):.1%}) | "
              f"{turned} ({turned / max(e['rw'], 1):.0%}) |")

    print("\nThe rule's agreement threshold (spread, hold and tolerance at their defaults): steps misclassified by "
          "the rule, and replays where assess() says what the ground truth says (converged and never lost)\n")
    sets = {"CARMEN logs": carmen, "synth": replays.get("synth", [])}
    sets = {k: v for k, v in sets.items() if v}
    print("| agreement >= | " + " | ".join(f"{k}: right called wrong | {k}: wrong called right | {k}: replays"
                                            for k in sets) + " |")
    print("| --- " * (1 + 3 * len(sets)) + "|")
    for thr in (0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9):
        cells = []
        for rs in sets.values():
            e = judge(rs, replace(rule, agreement=thr))
            cells += [f"{e['rw'] / max(e['n_right'], 1):.1%}", f"{e['wr'] / max(e['n_wrong'], 1):.1%}",
                      f"{e['match']}/{len(rs)}"]
        mark = " (default)" if thr == rule.agreement else ""
        print(f"| {thr:g}{mark} | " + " | ".join(cells) + " |")

    print(f"\nThe hold (agreement {rule.agreement:g}, tolerance {tol:g} m): replays where assess() says what the "
          "ground truth says (converged and never lost track); in brackets, quality alone says converged / the "
          "ground truth alone does\n")
    print("| hold | " + " | ".join(f"{k}: replays" for k in sets) + " |")
    print("| --- " * (1 + len(sets)) + "|")
    for hold in (5, 10, 20, 30):
        cells = []
        for rs in sets.values():
            e = judge(rs, replace(rule, hold=hold))
            cells.append(f"{e['match']}/{len(rs)} ({e['q_only']} / {e['g_only']})")
        print(f"| {hold}{' (default)' if hold == rule.hold else ''} | " + " | ".join(cells) + " |")

    print(f"\nThe agreement (tolerance {tol:g} m) at the true pose (what the map explains; every step), of the right "
          "and of the wrong steps: percentiles\n")
    print("| source | at the true pose: p5 / median | right steps: p5 / median | wrong steps: median / p95 |")
    print("| --- | --- | --- | --- |")
    for name, rs in groups.items():
        err, _ = labelled(rs)
        agree = np.concatenate([r["agreement"][tol] for r in rs])
        truth = np.concatenate([r["at_truth"] for r in rs])

        def pct(a, q):
            a = a[np.isfinite(a)]
            return " / ".join(f"{v:.2f}" for v in np.percentile(a, q)) if len(a) else "-"

        print(f"| {name} | {pct(truth, [5, 50])} | {pct(agree[err < RIGHT_M], [5, 50])} | "
              f"{pct(agree[err > WRONG_M], [50, 95])} |")

    print("\nPer replay: assess() against the ground truth (metrics.json: converged and never lost track)\n")
    print("| source | replays | both converged | both not | quality only | ground truth only | "
          "median conv. step, quality / ground truth |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    notes = []
    for name, rs in groups.items():
        e = judge(rs, rule)
        q = e["assessed"]
        qs = [a["converged_step"] for a in q if a["converged_step"] is not None]
        gs = [r["gt_converged_step"] for r in rs if r["gt_converged_step"] is not None]
        med = f"{np.median(qs):.0f}" if qs else "-", f"{np.median(gs):.0f}" if gs else "-"
        print(f"| {name} | {len(rs)} | {e['both']} | {e['neither']} | {e['q_only']} | {e['g_only']} | "
              f"{med[0]} / {med[1]} |")
        if name != "all":
            notes += [f"- {r['run']} trial {r['trial']}: quality converged at {a['converged_step']}, lost at "
                      f"{a['lost_steps']}; ground truth converged at {r['gt_converged_step']}, lost at {r['gt_lost']}"
                      for a, r in zip(q, rs, strict=True) if a["converged"] != r["held"] or a["lost_steps"]
                      or r["gt_lost"]]
    if notes:
        print("\nReplays where the two disagree or either lost track:\n\n" + "\n".join(notes))
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s")


def labelled(rs: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(errors of all steps, which are labelled: right or wrong)."""
    err = np.concatenate([r["error"] for r in rs])
    return err, (err < RIGHT_M) | (err > WRONG_M)


def judge(rs: list[dict], rule: QualityRule) -> dict:
    """The rule on replays `rs`: per step (misclassified labelled steps) and per replay (against `held`)."""
    err, keep = labelled(rs)
    right = err[keep] < RIGHT_M
    assessed = [assess(r["agreement"][rule.tolerance_m], r["spread"], r["states"], rule, r["kidnapped"],
                       updated=r["updated"]) for r in rs]
    good = np.concatenate([a["good_steps"] for a in assessed])[keep]
    pairs = [(a["converged"], r["held"]) for a, r in zip(assessed, rs, strict=True)]
    return {"assessed": assessed, "rw_mask": right & ~good, "rw": int((right & ~good).sum()),
            "wr": int((~right & good).sum()), "n_right": int(right.sum()), "n_wrong": int((~right).sum()),
            "match": sum(q == g for q, g in pairs), "both": sum(q and g for q, g in pairs),
            "neither": sum(not q and not g for q, g in pairs), "q_only": sum(q and not g for q, g in pairs),
            "g_only": sum(g and not q for q, g in pairs)}


if __name__ == "__main__":
    main()
