"""The building changes: time an incremental update against a full rebuild, then measure the bundles.

    .venv/bin/python benchmarks/update_workflow.py --preset tiny --work /tmp/upd [--room R] [--model DET]
        [--move-wall-m 0.5] [--iterations 30] [--trials 3] [--config demo] [--seed 0] [--workers N]

The building v1 is rendered, ingested and extracted. Then one room changes (`synth --change-area`, the room
with the most stops unless --room names one) and two ways to a current database are timed:
- rebuild: the whole changed floor is captured again (`synth --change-area R`), ingested and extracted;
- update: only the room is captured again (`synth --change-area R --area R`), ingested, merged with
  `update` and extracted with `extract --reuse` from v1's descriptors.
Synth stands in for the mapping team's capture; its time is printed apart from the processing time.
Both ways must end at the same descriptors: the update's tables are compared with the rebuild's for
the images they share (the stops of the changed room and every unchanged stop), and the changelog is
printed. Without --model a detector is trained for --iterations (30: enough to describe images for the
times, which do not depend on its quality; train it as the demo does for figures that mean something).
With --move-wall-m the change also moves an interior wall of the room, and the re-capture covers both
rooms beside it. Prints the machine, a table of seconds per step and the ratio.

Then the bundles: v1 (exported from the building before the change) and v2 (`export --parent v1` from the
update). `check` of v1 and of v2 against the changed floor (per area: verdict, recall@4, views like the
bundle's, endpoints on walls), and `evaluate` (--trials) of v1 on the building before the change, of v1 on
the changed building and of v2 on the changed building: v1's loss, and whether v2 is back to v1's figures.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def timed(label: str, times: dict, fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    times[label] = time.perf_counter() - t
    print(f"  {label}: {times[label]:.1f} s", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--room")
    ap.add_argument("--model", type=Path)
    ap.add_argument("--config", default="demo")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int)
    ap.add_argument("--move-wall-m", type=float, default=0.0)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--trials", type=int, default=3)
    args = ap.parse_args()

    import csv

    import pyarrow.parquet as pq

    from pipeline.config import load_config
    from pipeline.detection.train import run_train_detector
    from pipeline.ingest import run_ingest
    from pipeline.machine import machine_summary
    from pipeline.retrieval.extract import run_extract
    from pipeline.sitegen.presets import load_site_preset
    from pipeline.sitegen.synth import run_synth
    from pipeline.update.site_update import run_update

    print(json.dumps(machine_summary()))
    cfg = load_config(args.config)
    preset = load_site_preset(args.preset, {})
    w = args.work
    shutil.rmtree(w, ignore_errors=True)
    t: dict[str, float] = {}
    kw = {"seed": args.seed, "progress": False, "workers": args.workers}
    print("v1")
    v1 = timed("synth v1", t, run_synth, preset, outputs={"out": w / "v1"}, **kw)
    ing1 = timed("ingest v1", t, run_ingest, cfg, inputs={"site": v1}, outputs={"out": w / "v1-ing"},
                 progress=False)
    it = args.iterations
    model = args.model or timed(f"train detector ({it} it)", t, run_train_detector, load_config(
        args.config, [f"detector.iterations={it}", f"detector.checkpoint_every={it}"]), inputs={"data": ing1},
        outputs={"out": w / "det"}, progress=False)
    x1 = timed("extract v1", t, run_extract, cfg, inputs={"model": model, "data": ing1},
               outputs={"out": w / "v1-x"}, progress=False)
    with (v1 / "captures.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    ranked = [r for r, _ in Counter(r["room"] for r in rows if r["room"]).most_common()]
    if args.move_wall_m and not args.room:  # the busiest room one of whose walls can move
        from pipeline.sitegen.synth import build_scene
        from pipeline.sitegen.wall_move import choose_wall_move

        base = build_scene(preset, args.seed, False)
        ranked = [r for r in ranked if choose_wall_move(base, args.seed, args.move_wall_m, (r,)) is not None]
    room = args.room or ranked[0]
    print(f"change: room {room} ({sum(r['room'] == room for r in rows) // 6} of {len(rows) // 6} stops)")
    print("rebuild")
    full = timed("synth changed floor", t, run_synth, preset, outputs={"out": w / "v2-full"}, change_areas=(room,),
                 move_wall_m=args.move_wall_m, **kw)
    moved = json.loads((full / "synth_report.json").read_text()).get("wall_moved")
    rooms = tuple(sorted({room, *(moved["rooms"] if moved else ())}))
    if moved:
        print(f"wall moved {moved['distance_m']} m between {', '.join(moved['rooms'])}: {moved['from']} -> "
              f"{moved['to']}")
    ing_full = timed("ingest changed floor", t, run_ingest, cfg, inputs={"site": full},
                     outputs={"out": w / "v2-full-ing"}, progress=False)
    x_full = timed("extract changed floor", t, run_extract, cfg, inputs={"model": model, "data": ing_full},
                   outputs={"out": w / "v2-full-x"}, progress=False)
    print("update")
    sub = timed("synth changed room", t, run_synth, preset, outputs={"out": w / "v2-room"}, change_areas=(room,),
                areas=rooms, move_wall_m=args.move_wall_m, **kw)
    ing_sub = timed("ingest changed room", t, run_ingest, cfg, inputs={"site": sub},
                    outputs={"out": w / "v2-room-ing"}, progress=False)
    v2 = timed("update", t, run_update, cfg, inputs={"site_db": ing1, "new_data": ing_sub},
               outputs={"out": w / "v2-upd"}, progress=False)
    x_upd = timed("extract --reuse", t, run_extract, cfg, inputs={"model": model, "data": v2, "reuse": x1},
                  outputs={"out": w / "v2-upd-x"}, progress=False)

    # The update's descriptors of the stop views equal the rebuild's (same files, same describer).
    a, b = (pq.read_table(p / "ipa.parquet").to_pydict() for p in (x_upd, x_full))
    da, db = dict(zip(a["image_id"], a["descriptor"], strict=True)), dict(zip(b["image_id"], b["descriptor"],
                                                                              strict=True))
    stops = [i for i in da if not i.startswith("images/runs/")]
    same = sum(da[i] == db.get(i) for i in stops)
    print(f"stop views with descriptors equal to the rebuild's: {same} of {len(stops)}")
    log = json.loads((v2 / "changelog.json").read_text())
    print(f"changelog: areas {log['changed_areas']}, map {log['map']['cells_changed']} cells changed, kept "
          f"{log['totals']['stops_kept']} stops, added {log['totals']['stops_added']}")
    rep = json.loads((x_upd / "report.json").read_text())
    print(f"extract --reuse: computed {rep['computed_images']}, reused {rep['reuse']['reused_images']}")
    rebuild = t["ingest changed floor"] + t["extract changed floor"]
    update = t["ingest changed room"] + t["update"] + t["extract --reuse"]
    print("\n| way | capture (synth) s | processing s |\n| --- | --- | --- |")
    print(f"| rebuild | {t['synth changed floor']:.1f} | {rebuild:.1f} |")
    print(f"| update | {t['synth changed room']:.1f} | {update:.1f} |")
    print(f"processing, update / rebuild: {update / rebuild:.2f}; capture: "
          f"{t['synth changed room'] / t['synth changed floor']:.2f}")
    bundles(args, cfg, w, model, ing1, x1, v2, x_upd, ing_full)


def bundles(args, cfg, w: Path, model: Path, ing1: Path, x1: Path, v2: Path, x_upd: Path, ing_full: Path) -> None:
    """v1 and v2 bundles, checked against the changed floor and evaluated before and after the change."""
    from pipeline.bundle.check import run_check
    from pipeline.bundle.diff import next_version
    from pipeline.bundle.export import run_export
    from pipeline.evaluation.report import run_evaluate
    from pipeline.retrieval.database import run_build_index

    t: dict[str, float] = {}
    cfg = cfg.model_copy(update={"evaluate": cfg.evaluate.model_copy(update={"trials": args.trials})})
    v1v = cfg.export.version
    cfg2 = cfg.model_copy(update={"export": cfg.export.model_copy(update={"version": next_version(v1v)})})
    print("bundles")
    i1 = timed("build-index v1", t, run_build_index, cfg, inputs={"descriptors": x1}, outputs={"out": w / "v1-index"})
    b1 = timed("export v1", t, run_export, cfg, inputs={"model": model, "index": i1, "data": ing1},
               outputs={"out": w / "bundles"}, progress=False)
    i2 = timed("build-index v2", t, run_build_index, cfg, inputs={"descriptors": x_upd},
               outputs={"out": w / "v2-index"})
    b2 = timed("export v2 --parent v1", t, run_export, cfg2, inputs={"parent": b1, "model": model, "index": i2,
                                                                      "data": v2}, outputs={"out": w / "bundles"},
               progress=False)
    log = json.loads((b2 / "changelog.json").read_text())
    print(f"v2 changelog: areas {log['areas_changed']}, stops {log['stops']}, map cells {log['map']['cells_changed']}"
          f", inputs {log['components']}")
    checks = {}
    for name, b, data in (("v1 before", b1, ing1), ("v1", b1, ing_full), ("v2", b2, ing_full)):
        floor = "the building before the change" if name == "v1 before" else "the changed floor"
        out = timed(f"check {name.split()[0]} on {floor}", t, run_check, cfg, inputs={"bundle": b, "data": data},
                    outputs={"out": w / f"check-{name.replace(' ', '-')}"}, localize=False, progress=False)
        checks[name] = json.loads((out / "report.json").read_text())
        print(f"  {name.split()[0]} on {floor}: " + " ".join(checks[name]["recommendation"]["text"]))

    def f(v, fmt="{:.2f}"):
        return "-" if v is None else fmt.format(v)

    print("\n| bundle, floor | areas judged | re-capture | update map | m2 changed, largest area |\n"
          "| --- | --- | --- | --- | --- |")
    for name, doc in checks.items():
        judged = [e for e in doc["areas"].values() if e["verdict"] != "too few data"]
        largest = max(((e.get("map") or {}).get("changed_m2") or 0.0 for e in judged), default=0.0)
        print(f"| {name} | {len(judged)} | {', '.join(doc['recommendation']['recapture']) or '-'} | "
              f"{', '.join(doc['recommendation']['update_map']) or '-'} | {largest:.2f} |")
    print("\n| area | v1 verdict | v1 recall@4 | v1 views changed | v1 endpoints on walls | v1 m2 changed | "
          "v2 verdict | v2 recall@4 | v2 views changed |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for key in sorted(set(checks["v1"]["areas"]) | set(checks["v2"]["areas"])):
        a, b = checks["v1"]["areas"].get(key, {}), checks["v2"]["areas"].get(key, {})
        if a.get("verdict", "too few data") == "too few data" and b.get("verdict", "too few data") == "too few data":
            continue
        am, an = a.get("map") or {}, a.get("new") or {}
        print(f"| {key} | {a.get('verdict')} | {f(an.get('recall_at_4'))} | "
              f"{f(a.get('changed_view_share'), '{:.0%}')} | {f(am.get('endpoint_share_on_walls'), '{:.0%}')} | "
              f"{f(am.get('changed_m2'))} | {b.get('verdict')} | {f((b.get('new') or {}).get('recall_at_4'))} | "
              f"{f(b.get('changed_view_share'), '{:.0%}')} |")
    ev = {}
    for label, b, data in (("v1, building before", b1, ing1), ("v1, changed building", b1, ing_full),
                           ("v2, changed building", b2, ing_full)):
        out = timed(f"evaluate {label}", t, run_evaluate, cfg, inputs={"bundle": b, "data": data},
                    outputs={"out": w / ("eval-" + label.replace(", ", "-").replace(" ", "_"))}, progress=False)
        ev[label] = json.loads((out / "metrics.json").read_text())["summary"]["proposed"]
    print(f"\n| bundle, building ({args.trials} trials per run) | converged and held | lost track | median step | "
          "error p90 (m) | median error converged (m) | kidnaps recovered (within 15) |\n"
          "| --- | --- | --- | --- | --- | --- | --- |")
    for label, s in ev.items():
        print(f"| {label} | {s['converged']}/{s['replays']} | {s['lost_track']} | {s['converged_step_median']} | "
              f"{s['error_p90_all_m']} | {s['error_median_converged_m']} | {s['recovered']}/{s['kidnaps']} "
              f"({s['recovered_within_15']}) |")


if __name__ == "__main__":
    main()
