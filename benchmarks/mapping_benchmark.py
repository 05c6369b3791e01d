"""Time occupancy mapping with known poses on the real CARMEN logs.

    .venv/bin/python benchmarks/mapping_benchmark.py [--carmen-dir DIR] [--resolution 0.05] [--repeat 3]

Prints the machine (platform, CPU, cores, Python and numpy versions), then per log: parse time, the
best of `--repeat` map-building times, scans per second, map size and the endpoint-on-occupied share.
Only mapping is timed (no odometry, Parquet or preview), single process, as `siteloc ingest-log` runs it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.config import MappingConfig  # noqa: E402
from pipeline.io.carmen import read_carmen  # noqa: E402
from pipeline.machine import machine_info  # noqa: E402,F401  (re-exported for the other benchmarks)
from pipeline.mapping.occupancy import build_occupancy_map, endpoint_occupied_share  # noqa: E402

LOGS = ["intel", "aces", "csail", "fhw", "freiburg-079"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--carmen-dir", type=Path, default=REPO.parent / "shared" / "data" / "carmen")
    parser.add_argument("--resolution", type=float, default=0.05)
    parser.add_argument("--repeat", type=int, default=3, help="map each log this many times, report the best")
    parser.add_argument("--logs", nargs="*", default=LOGS)
    args = parser.parse_args()

    print("\n".join(machine_info()))
    cfg = MappingConfig(resolution=args.resolution)
    print(f"mapping: resolution {cfg.resolution} m, chunk_scans {cfg.chunk_scans}, best of {args.repeat}\n")
    header = (
        f"{'log':<14}{'scans':>6}{'beams':>6}{'parse s':>9}{'map s':>8}{'scans/s':>9}{'cells':>13}"
        f"{'tol0':>7}{'tol1':>7}"
    )
    print(header)
    print("-" * len(header))
    for name in args.logs:
        path = args.carmen_dir / f"{name}-corrected.log.gz"
        if not path.is_file():
            print(f"{name:<14} missing: {path}")
            continue
        t0 = time.perf_counter()
        log = read_carmen(path)
        parse_s = time.perf_counter() - t0
        geometry = (log.angle_min, log.angle_increment, log.range_max)
        best = float("inf")
        for _ in range(max(args.repeat, 1)):
            t0 = time.perf_counter()
            occ = build_occupancy_map(log.poses, log.ranges, *geometry, cfg, progress=False)
            best = min(best, time.perf_counter() - t0)
        shares = [
            endpoint_occupied_share(occ, log.poses, log.ranges, *geometry, k, max_range=cfg.max_range_m) for k in (0, 1)
        ]
        print(
            f"{name:<14}{log.n_scans:>6}{log.n_beams:>6}{parse_s:>9.2f}{best:>8.2f}{log.n_scans / best:>9.0f}"
            f"{f'{occ.width}x{occ.height}':>13}{shares[0]:>7.3f}{shares[1]:>7.3f}"
        )


if __name__ == "__main__":
    main()
