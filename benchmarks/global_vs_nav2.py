"""Global localization on the real logs: siteloc's filter against nav2's (PyPI `amcl` 0.1.2), same run.

    .venv/bin/python benchmarks/global_vs_nav2.py [--data data/carmen] [--trials 3] [--max-steps 600]
        [--logs intel-corrected ...]

Both filters start knowing nothing and get the log's scans and (synthesised) odometry, 500 to 5000
particles with KLD-sampling, alpha_slow 0.001 / alpha_fast 0.1, 60 beams, the same motion alphas and
sensor parameters. Ours starts uniform over the free space (likelihood field, its default, and the beam
model). The binding of nav2's filter has no uniform initialisation (nav2's global-localization service is
not exposed), so it starts from the widest Gaussian it takes: centred on the map's free space with a
standard deviation of half the free space's extent in x and y and pi in heading; its own augmented-MCL
injections then do what they can. nav2 has no seed, so its trials differ by chance only.

"Converged": position error under 0.5 m for 10 consecutive steps (or to the end). Prints the machine and
a Markdown table of converged replays and median convergence steps per log and filter.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402
from benchmarks.nav2_peer import make_nav2  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.evaluation.metrics import first_settled  # noqa: E402
from pipeline.evaluation.replay import load_run  # noqa: E402
from pipeline.io.map_yaml import read_map  # noqa: E402
from pipeline.localize import replay_one  # noqa: E402
from pipeline.runtime.grid import LaserMap  # noqa: E402

LOGS = ["intel-corrected", "aces-corrected", "csail-corrected", "fhw-corrected", "freiburg-079-corrected"]


def nav2_replay(occ, lmap, run, fcfg) -> np.ndarray:
    import amcl

    loc = make_nav2(occ, fcfg, min_particles=fcfg.min_particles, max_particles=fcfg.max_particles,
                    max_beams=fcfg.sensor.max_beams, recovery=True)
    rows, cols = np.nonzero(lmap.free)
    xs = lmap.origin_x + (cols + 0.5) * lmap.resolution
    ys = lmap.origin_y + (rows + 0.5) * lmap.resolution
    centre = ((xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2)
    half = ((xs.max() - xs.min()) / 2, (ys.max() - ys.min()) / 2)
    loc.set_initial_pose(amcl.Vector3D(centre[0], centre[1], 0.0),
                         amcl.create_diagonal_covariance(half[0] ** 2, half[1] ** 2, math.pi ** 2))
    bearings = run.angle_min + run.angle_increment * np.arange(run.ranges.shape[1])
    errors = np.empty(len(run))
    for i in range(len(run)):
        scan = amcl.create_laser_scan_from_list(
            [[float(r), float(b)] for r, b in zip(run.ranges[i], bearings, strict=True)], run.range_max)
        loc.update(scan, amcl.Vector3D(*run.odom[i]))
        p = loc.get_pose_mean()
        errors[i] = math.hypot(p.x - run.gt[i, 0], p.y - run.gt[i, 1])
    return errors


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO / "data" / "carmen")
    ap.add_argument("--logs", nargs="*", default=LOGS)
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--max-steps", type=int, default=600)
    args = ap.parse_args()
    print("\n".join(machine_info()))
    try:
        import amcl  # noqa: F401
    except ImportError:
        sys.exit("the peer is missing: pip install amcl==0.1.2 (the benchmarks extra)")
    from dataclasses import replace

    base = load_config("demo").filter
    base = base.model_copy(update={"sensor": base.sensor.model_copy(update={"beam_skip": False})})  # as nav2's
    filters = {"ours LF": base, "ours beam": base.model_copy(update={"sensor": base.sensor.model_copy(
        update={"model": "beam"})})}
    rows = []
    for log in args.logs:
        data = args.data / log
        if not (data / "map.yaml").is_file():
            print(f"skip {log}: no {data / 'map.yaml'} (run siteloc ingest-log first)")
            continue
        occ = read_map(data / "map.yaml")
        lmap = LaserMap.from_occupancy(occ, base.sensor.max_distance)
        run = load_run(next((data / "runs").glob("*.parquet")))
        n = min(len(run), args.max_steps)
        run = replace(run, odom=run.odom[:n], gt=run.gt[:n], ranges=run.ranges[:n], kidnapped=run.kidnapped[:n])
        results: dict[str, list] = {}
        for trial in range(args.trials):
            for name, fcfg in filters.items():
                t0 = time.perf_counter()
                rep = replay_one(run, lmap, fcfg, (0.0, 0.0, 0.0), "uniform", trial)
                err = np.hypot(*(rep["pose"][:, :2] - run.gt[:, :2]).T)
                results.setdefault(name, []).append((first_settled(err, 0, 0.5, 10), time.perf_counter() - t0))
            t0 = time.perf_counter()
            err = nav2_replay(occ, lmap, run, base)
            results.setdefault("nav2", []).append((first_settled(err, 0, 0.5, 10), time.perf_counter() - t0))
            print(f"{log} trial {trial}: " + ", ".join(f"{k} {v[-1][0]}" for k, v in results.items()), flush=True)
        for name, res in results.items():
            steps = [s for s, _ in res if s is not None]
            rows.append((log, name, len(steps), len(res), float(np.median(steps)) if steps else None,
                         float(np.mean([t for _, t in res]))))

    print(f"\n| log | filter | converged | median convergence step | s per replay ({args.max_steps} steps max) |")
    print("| --- | --- | --- | --- | --- |")
    for log, name, ok, total, med, secs in rows:
        print(f"| {log.removesuffix('-corrected')} | {name} | {ok}/{total} | {'-' if med is None else f'{med:.0f}'} "
              f"| {secs:.0f} |")


if __name__ == "__main__":
    main()
