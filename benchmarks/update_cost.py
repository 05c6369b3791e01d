"""Time per filter update of this tree against another revision, alternating, on one ingested log.

    .venv/bin/python benchmarks/update_cost.py --against 16d024a [--data /tmp/carmen/intel-corrected] [--rounds 3]

Each round replays the log's first run once per tree (tracking from the true first pose, the `demo` filter),
in a fresh process so neither inherits the other's modules; the revision is checked out into a temporary git
worktree. Prints the machine, every round's ms per update and the ratios of the best and of the median of each
(shared machines vary by tens of percent between rounds: run 9 rounds or more).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402

REPLAY = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from pipeline.config import load_config
from pipeline.evaluation.replay import load_run
from pipeline.io.map_yaml import read_map
from pipeline.localize import _mount
from pipeline.runtime.amcl import AdaptiveMCL
from pipeline.runtime.grid import LaserMap
from pipeline.runtime.sensor import Scan
data = Path(sys.argv[2])
cfg = load_config("demo")
run = load_run(sorted((data / "runs").glob("*.parquet"))[0])
lmap = LaserMap.from_occupancy(read_map(data / "map.yaml"), cfg.filter.sensor.max_distance)
scans = [Scan(r, run.angle_min, run.angle_increment, run.range_max) for r in run.ranges]
f = AdaptiveMCL(lmap, cfg.filter, range_max=run.range_max, base_from_laser=_mount(data))
f.init_pose(run.gt[0])
f.update(run.odom[0], scans[0])  # compiles the kernels
t, n = time.perf_counter(), 0
for i in range(1, len(scans)):
    n += f.update(run.odom[i], scans[i]).updated
print(json.dumps({"ms": (time.perf_counter() - t) / n * 1000, "updates": n}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", required=True, help="git revision to compare with (e.g. a commit before a change)")
    ap.add_argument("--data", type=Path, default=REPO / "data" / "carmen" / "intel-corrected")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    print("\n".join(machine_info()))
    with tempfile.TemporaryDirectory(prefix="siteloc-update-cost-") as tmp:
        other = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-q", "--detach", str(other), args.against],
                       check=True)
        try:
            times: dict[str, list[float]] = {args.against: [], "this tree": []}
            for _ in range(args.rounds):
                for label, tree in ((args.against, other), ("this tree", REPO)):
                    out = subprocess.run([sys.executable, "-c", REPLAY, str(tree), str(args.data)], check=True,
                                         capture_output=True, text=True, cwd=tmp).stdout
                    got = json.loads(out.strip().splitlines()[-1])
                    times[label].append(got["ms"])
                    print(f"{label:12s} {got['ms']:.3f} ms per update ({got['updates']} updates)", flush=True)
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(other)], check=False)
    for name, pick in (("best", min), ("median", statistics.median)):
        t = {k: pick(v) for k, v in times.items()}
        print(f"{name} of {args.rounds}: {args.against} {t[args.against]:.3f} ms, this tree {t['this tree']:.3f} ms, "
              f"this tree / {args.against} = {t['this tree'] / t[args.against]:.2f}")


if __name__ == "__main__":
    main()
