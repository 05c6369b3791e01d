"""Time per filter update: siteloc's AdaptiveMCL against nav2's particle filter (PyPI `amcl` 0.1.2), one run.

    .venv/bin/python benchmarks/filter_vs_nav2.py [--data data/carmen/intel-corrected] [--updates 20]
        [--particles 500 2000 5000 10000] [--beams 60 271 1081] [--budget-s 6]

Both filters get the same map (the intel log's, 5 cm), the same odometry and the same scans: 1081-beam
270-degree scans cast (noise-free plus 1 cm noise) on that map along the log's ground truth, so every beam
count can be asked of one scan; each filter subsamples to `max_beams` itself, and both use the same
sensor-model parameters and odometry noise alphas (ours: the `filter` config). Particle counts are fixed
(min = max = N; ours with method `mcl`), every call is a full update (ours with update_min_d = 0; the
selected steps are 0.3 m apart so nav2's 0.2 m gate always opens too). Both run on one thread.

Printed per (N, beams): nav2's ms per update (beam model, its only one), ours with the beam model and the
ratio, ours with the likelihood field (numba kernel) and the same with the numpy twin kernel. nav2 is
stopped for a configuration after --budget-s seconds (at least 3 updates) so the table finishes; the
number of updates timed is printed beside each figure. Also printed: both filters' median tracking error
on the timed steps at N = 2000, 60 beams, as a check that both were really localizing.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402
from benchmarks.nav2_peer import make_nav2  # noqa: E402
from pipeline.config import FilterConfig  # noqa: E402
from pipeline.evaluation.replay import load_run  # noqa: E402
from pipeline.io.map_yaml import read_map  # noqa: E402
from pipeline.runtime.amcl import AdaptiveMCL  # noqa: E402
from pipeline.runtime.grid import LaserMap  # noqa: E402
from pipeline.runtime.sensor import Scan  # noqa: E402
from pipeline.sitegen.laser import LaserScanner  # noqa: E402

RANGE_MAX = 30.0


def select_steps(gt: np.ndarray, spacing: float, n: int) -> list[int]:
    steps, last = [0], gt[0, :2]
    for i in range(1, len(gt)):
        if math.hypot(*(gt[i, :2] - last)) >= spacing:
            steps.append(i)
            last = gt[i, :2]
        if len(steps) >= n + 1:
            break
    return steps


def ours(lmap, odom, gt, scans, n, beams, model, backend="auto", budget_s=1e9):
    cfg = FilterConfig(method="mcl", min_particles=n, max_particles=n, update_min_d=0.0, update_min_a_deg=0.0,
                       sensor={"model": model, "max_beams": beams, "beam_skip": False})  # as nav2's default
    f = AdaptiveMCL(lmap, cfg, range_max=RANGE_MAX)
    if backend != "auto":
        f.sensor.backend = backend
    f.init_pose(gt[0], std_xy=0.1, std_theta=0.05)
    f.update(odom[0], scans[0])  # compiles the kernels; not timed
    times, errors = [], []
    t_start = time.perf_counter()
    for k in range(1, len(scans)):
        t0 = time.perf_counter()
        r = f.update(odom[k], scans[k])
        times.append(time.perf_counter() - t0)
        errors.append(math.hypot(*(r.pose[:2] - gt[k, :2])))
        if time.perf_counter() - t_start > budget_s and len(times) >= 3:
            break
    return 1000 * float(np.mean(times)), len(times), float(np.median(errors))


def nav2(occ, odom, gt, scans, n, beams, budget_s):
    import amcl

    loc = make_nav2(occ, FilterConfig(sensor={"model": "beam"}), min_particles=n, max_particles=n, max_beams=beams,
                    recovery=False)
    loc.set_initial_pose(amcl.Vector3D(*gt[0]), amcl.create_diagonal_covariance(0.01, 0.01, 0.0025))
    lists = [amcl.create_laser_scan_from_list([[float(r), float(b)] for r, b in zip(sc.ranges, sc.angles, strict=True)],
                                              RANGE_MAX) for sc in scans]  # converted before timing
    loc.update(lists[0], amcl.Vector3D(*odom[0]))
    times, errors = [], []
    t_start = time.perf_counter()
    for k in range(1, len(scans)):
        t0 = time.perf_counter()
        loc.update(lists[k], amcl.Vector3D(*odom[k]))
        times.append(time.perf_counter() - t0)
        p = loc.get_pose_mean()
        errors.append(math.hypot(p.x - gt[k, 0], p.y - gt[k, 1]))
        if time.perf_counter() - t_start > budget_s and len(times) >= 3:
            break
    return 1000 * float(np.mean(times)), len(times), float(np.median(errors))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO / "data" / "carmen" / "intel-corrected")
    ap.add_argument("--updates", type=int, default=20)
    ap.add_argument("--particles", type=int, nargs="*", default=[500, 2000, 5000, 10000])
    ap.add_argument("--beams", type=int, nargs="*", default=[60, 271, 1081])
    ap.add_argument("--budget-s", type=float, default=6.0)
    args = ap.parse_args()
    print("\n".join(machine_info()))
    try:
        import amcl  # noqa: F401
    except ImportError:
        sys.exit("the peer is missing: pip install amcl==0.1.2 (the benchmarks extra)")
    occ = read_map(args.data / "map.yaml")
    run = load_run(next((args.data / "runs").glob("*.parquet")))
    lmap = LaserMap.from_occupancy(occ, 2.0)
    steps = select_steps(run.gt, 0.3, args.updates)
    gt, odom = run.gt[steps], run.odom[steps]
    scanner = LaserScanner(occ, beams=1081, fov_deg=270.0, range_max=RANGE_MAX, noise_sigma=0.01, dropout=0.0, seed=0)
    ranges = scanner.cast_many(gt)
    scans = [Scan(r.astype(np.float64), scanner.angle_min, scanner.angle_increment, RANGE_MAX) for r in ranges]
    print(f"map: {args.data.name}, {occ.width} x {occ.height} cells at {occ.resolution} m; {len(scans) - 1} updates "
          f"0.3 m apart; scans 1081 beams over 270 degrees (cast on the map)\n")
    print("| particles | beams | nav2 beam (ms) | ours beam (ms) | nav2 / ours | ours LF numba (ms) "
          "| ours LF numpy (ms) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    checks = {}
    for n in args.particles:
        for b in args.beams:
            nv, nk, nerr = nav2(occ, odom, gt, scans, n, b, args.budget_s)
            ob, ok_, oerr = ours(lmap, odom, gt, scans, n, b, "beam")
            lf, _, lerr = ours(lmap, odom, gt, scans, n, b, "likelihood_field")
            lfn, lk, _ = ours(lmap, odom, gt, scans, n, b, "likelihood_field", backend="numpy", budget_s=args.budget_s)
            print(f"| {n} | {b} | {nv:.1f} ({nk}) | {ob:.2f} ({ok_}) | {nv / ob:.1f}x | {lf:.2f} | {lfn:.1f} ({lk}) |",
                  flush=True)
            if (n, b) == (2000, 60):
                checks = {"nav2": nerr, "ours beam": oerr, "ours LF": lerr}
    if checks:
        print("\nmedian tracking error on the timed steps, 2000 particles x 60 beams: "
              + ", ".join(f"{k} {v:.3f} m" for k, v in checks.items()))


if __name__ == "__main__":
    main()
