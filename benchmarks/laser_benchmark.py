"""Time simulated laser scans on the reference site's office floor (about 40 x 30 m at 5 cm).

    .venv/bin/python benchmarks/laser_benchmark.py [--preset office] [--seed 0] [--poses 300] [--batch 50]

Prints the machine (platform, CPU, cores, Python and numpy versions), the map, then ms per scan and rays
per second of `LaserScanner` (sphere tracing on the distance field with exact DDA near obstacles), one
scan per call and `--batch` poses per call, and, as a peer in the same run on the same poses, the obvious
numpy alternative: a brute-force ray march sampling every beam each half cell up to range_max. Both are
noise-free; their agreement (share of beams within one cell of each other) is printed too.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.mapping_benchmark import machine_info  # noqa: E402
from pipeline.io.map_yaml import OccupancyMap  # noqa: E402
from pipeline.sitegen.laser import LaserScanner, rasterise_map  # noqa: E402
from pipeline.sitegen.presets import load_site_preset  # noqa: E402
from pipeline.sitegen.routes import clearance_field  # noqa: E402


def build_scene(preset_name: str, seed: int):
    from pipeline.sitegen.synth import build_scene as build

    return build(load_site_preset(preset_name), seed, False)


def brute_force(occ: OccupancyMap, poses: np.ndarray, angles: np.ndarray, range_max: float) -> np.ndarray:
    """First occupied sample of every beam, sampled each half cell: (N, beams) ranges, range_max if none."""
    occupied = occ.occupied
    ts = np.arange(0.5 * occ.resolution, range_max, 0.5 * occ.resolution)
    out = np.empty((len(poses), len(angles)))
    for k, (x, y, theta) in enumerate(poses):
        a = theta + angles
        row, col = occ.world_to_cell(x + np.cos(a)[:, None] * ts, y + np.sin(a)[:, None] * ts)
        inside = occ.contains(row, col)
        hit = np.zeros(row.shape, dtype=bool)
        hit[inside] = occupied[row[inside], col[inside]]
        first = hit.argmax(axis=1)
        out[k] = np.where(hit.any(axis=1), ts[first], range_max)
    return out


def best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="office")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=float, default=0.05)
    parser.add_argument("--poses", type=int, default=300, help="poses for the sphere tracer")
    parser.add_argument("--brute-poses", type=int, default=30, help="poses for the brute-force peer (slow)")
    parser.add_argument("--batch", type=int, default=50, help="poses per cast_many call")
    args = parser.parse_args()

    print("\n".join(machine_info()))
    t0 = time.perf_counter()
    scene = build_scene(args.preset, args.seed)
    occ = rasterise_map(scene, args.resolution)
    t_map = time.perf_counter() - t0
    t0 = time.perf_counter()
    scanner = LaserScanner(occ, noise_sigma=0.0, dropout=0.0)
    t_edt = time.perf_counter() - t0
    b = scene.bounds
    print(f"map: {args.preset} seed {args.seed}, {b.w:.1f} x {b.h:.1f} m, {occ.width} x {occ.height} cells "
          f"at {occ.resolution} m; scene + rasterise {t_map * 1e3:.0f} ms, distance field {t_edt * 1e3:.0f} ms")

    rng = np.random.default_rng(args.seed)
    rows, cols = np.nonzero(clearance_field(occ) >= 0.3)
    pick = rng.choice(rows.size, size=args.poses)
    x, y = occ.cell_to_world(rows[pick], cols[pick])
    poses = np.column_stack([x, y, rng.uniform(-np.pi, np.pi, args.poses)])
    beams = scanner.beams

    single = best_of(lambda: [scanner.cast(p, noisy=False) for p in poses]) / args.poses
    batches = [poses[i : i + args.batch] for i in range(0, len(poses), args.batch)]
    batched = best_of(lambda: [scanner.cast_many(p, noisy=False) for p in batches]) / args.poses
    peer_poses = poses[: args.brute_poses]
    brute = best_of(lambda: brute_force(occ, peer_poses, scanner.angles, scanner.range_max), 1) / len(peer_poses)

    ours = scanner.cast_many(peer_poses, noisy=False)
    theirs = brute_force(occ, peer_poses, scanner.angles, scanner.range_max)
    agree = float(np.mean(np.abs(ours - theirs) <= occ.resolution))
    print(f"beams per scan: {beams}, range_max {scanner.range_max} m, no-return share {np.mean(ours >= 30):.4f}")
    rows_out = [
        ("sphere tracing, 1 scan per call", single),
        (f"sphere tracing, {args.batch} scans per call", batched),
        ("brute-force march (half-cell steps)", brute),
    ]
    for label, per_scan in rows_out:
        print(f"{label:40s} {per_scan * 1e3:8.2f} ms/scan {beams / per_scan:14,.0f} rays/s")
    print(f"speed-up over brute force: {brute / single:.1f}x (1 scan per call), {brute / batched:.1f}x (batched)")
    print(f"agreement with brute force: {agree:.4f} of beams within one cell ({len(peer_poses)} scans)")


if __name__ == "__main__":
    main()
