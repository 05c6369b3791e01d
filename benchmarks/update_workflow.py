"""Time an incremental update against a full rebuild, from the capture to the descriptors.

    .venv/bin/python benchmarks/update_workflow.py --preset tiny --work /tmp/upd [--room R] [--model DET]
                                                   [--config demo] [--seed 0] [--workers N]

The building v1 is rendered, ingested and extracted. Then one room changes (`synth --change-area`, the room
with the most stops unless --room names one) and two ways to a current database are timed:
- rebuild: the whole changed floor is captured again (`synth --change-area R`), ingested and extracted;
- update: only the room is captured again (`synth --change-area R --area R`), ingested, merged with
  `update` and extracted with `extract --reuse` from v1's descriptors.
Synth stands in for the mapping team's capture; its time is printed apart from the processing time.
Both ways must end at the same descriptors: the update's tables are compared with the rebuild's for
the images they share (the stops of the changed room and every unchanged stop), and the changelog is
printed. Without --model a detector is trained for 30 iterations (it only has to describe images: the
times do not depend on its quality). Prints the machine, a table of seconds per step and the ratio.
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
    model = args.model or timed("train detector (30 it)", t, run_train_detector, load_config(
        args.config, ["detector.iterations=30", "detector.checkpoint_every=30"]), inputs={"data": ing1},
        outputs={"out": w / "det"}, progress=False)
    x1 = timed("extract v1", t, run_extract, cfg, inputs={"model": model, "data": ing1},
               outputs={"out": w / "v1-x"}, progress=False)
    with (v1 / "captures.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    room = args.room or Counter(r["room"] for r in rows if r["room"]).most_common(1)[0][0]
    print(f"change: room {room} ({sum(r['room'] == room for r in rows) // 6} of {len(rows) // 6} stops)")
    print("rebuild")
    full = timed("synth changed floor", t, run_synth, preset, outputs={"out": w / "v2-full"}, change_areas=(room,),
                 **kw)
    ing_full = timed("ingest changed floor", t, run_ingest, cfg, inputs={"site": full},
                     outputs={"out": w / "v2-full-ing"}, progress=False)
    x_full = timed("extract changed floor", t, run_extract, cfg, inputs={"model": model, "data": ing_full},
                   outputs={"out": w / "v2-full-x"}, progress=False)
    print("update")
    sub = timed("synth changed room", t, run_synth, preset, outputs={"out": w / "v2-room"}, change_areas=(room,),
                areas=(room,), **kw)
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


if __name__ == "__main__":
    main()
