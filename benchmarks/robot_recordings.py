"""Issue 52's targets on generated robot recordings: every trait tracked, global localization, long recordings.

    .venv/bin/python benchmarks/robot_recordings.py [--parts traits office long] [--work DIR]
        [--cases NAME ...] [--office-seeds 10] [--office-stops 12] [--office-seconds S]
        [--long-minutes 5 10 20] [--long-write-bag no yes] [--set KEY=VALUE]

Recordings come from `tests/fixtures/robot_recordings.py` (laser + odometry as robots write them, with the
quirks a `Traits` names) and are replayed as `siteloc localize --bag` does (`run_localize_bag`, `demo` config,
filter.seed 3). The truth is the one `record()` returns (the fixture's floor frame), never the recording's
own reference, so recordings without a map frame are measured alike.

* traits: one recording per trait (each `Traits` field on its own) and per map variant, the whole default
  drive, `--init pose` at the first true pose: median and p90 position error, and whether the median is
  within 0.05 m (the target).
* office: a laser-only recording (no reference) of a drive through the office reference site's occupancy
  map (`pipeline.sitegen`, no rendering), replayed from a uniform start over `--office-seeds` seeds (trial t:
  filter seed + t): converged = `replay_metrics`' "held" (settled under 0.5 m for 10 steps, never lost track
  after), beside the quality rule's own verdict (no truth). Target: held in >= 9 of 10 seeds.
* long: a 40 Hz laser-only recording of `--long-minutes` minutes replayed with `--init pose` on one core
  (each replay in a fresh process: OMP/NUMBA/OpenBLAS/MKL threads 1, affinity to CPU 0): wall time against
  the recording's duration and the process's peak RSS (VmHWM), with and without `--write-bag`.

Prints the machine, then a Markdown table per part.
"""

from __future__ import annotations

import os
import sys

THREAD_VARS = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
if "--child" in sys.argv:  # a long replay's process: one thread everywhere, set before numpy is imported
    for _var in THREAD_VARS:
        os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from tests.fixtures import robot_recordings as rr  # noqa: E402
from tests.fixtures.robot_recordings import Traits  # noqa: E402

TARGET_M = 0.05  # the tracking target: median position error
PARTS = ("traits", "office", "long")


@dataclass(frozen=True)
class Case:
    name: str
    traits: Traits = Traits()
    map_opts: dict = field(default_factory=dict)  # res, world_res, pad, mode, negate, origin


CASES = [
    Case("default (mcap, tf odometry)"),
    Case("laser_yaw_deg 90", Traits(laser_yaw_deg=90.0)),
    Case("laser_yaw_deg 180", Traits(laser_yaw_deg=180.0)),
    Case("laser_upside_down", Traits(laser_upside_down=True)),
    Case("laser_upside_down + yaw 90", Traits(laser_upside_down=True, laser_yaw_deg=90.0)),
    Case("base_frame base_footprint", Traits(base_frame="base_footprint")),
    Case("base_footprint_above", Traits(base_footprint_above=True)),
    Case("slash (bag)", Traits(slash=True, fmt="bag")),
    Case("legacy_tf (bag)", Traits(legacy_tf=True, fmt="bag")),
    Case("odometry topic", Traits(odometry="topic")),
    Case("odometry both, topic drift 0.05", Traits(odometry="both", odom_topic_drift=0.05)),
    Case("no_return zero", Traits(no_return="zero")),
    Case("no_return nan", Traits(no_return="nan")),
    Case("no_return beyond", Traits(no_return="beyond")),
    Case("below_min_share 0.05", Traits(below_min_share=0.05)),
    Case("beam_jitter 2", Traits(beam_jitter=2)),
    Case("clockwise", Traits(clockwise=True)),
    Case("rate_hz 40 + bursts_and_gaps", Traits(rate_hz=40.0, bursts_and_gaps=True)),
    Case("rate_hz 5", Traits(rate_hz=5.0)),
    Case("odom_origin (1000, -500, 1.0)", Traits(odom_origin=(1000.0, -500.0, 1.0))),
    Case("fmt db3", Traits(fmt="db3")),
    Case("reference False", Traits(reference=False)),
    Case("map resolution 0.025", map_opts={"res": 0.025}),
    Case("map resolution 0.1", map_opts={"res": 0.1}),
    Case("map resolution 0.1, world 0.025", map_opts={"res": 0.1, "world_res": 0.025}),
    Case("map mode scale", map_opts={"mode": "scale"}),
    Case("map mode raw", map_opts={"mode": "raw"}),
    Case("map negate 1", map_opts={"negate": 1}),
    Case("map padded 20 m", map_opts={"pad": 20.0}),
    # The recording's map -> odom would be in the unturned grid frame, which contradicts a map.yaml whose
    # origin turns the grid: recorded without a reference, as a robot on that map would not publish one.
    Case("map origin (3, -2, 0.6 rad)", Traits(reference=False), map_opts={"origin": (3.0, -2.0, 0.6)}),
]


def slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")[:48]


def bag_path(folder: Path, traits: Traits) -> Path:
    return folder / ("rec.bag" if traits.fmt == "bag" else "rec")  # ROS 2: a bag folder (mcap or db3)


def wrap(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def read_estimates(out: Path):
    import pandas as pd

    return pd.read_parquet(out / "estimates.parquet")


def steps_to_scans(out: Path, run: str, n_steps: int, rec) -> np.ndarray:
    """Index into the recording's scans (rec.gt) of each replay step: one step per scan when none was dropped,
    else matched by the steps' stamps (the TUM file's, relative to the first scan)."""
    if n_steps == len(rec.gt):
        return np.arange(n_steps)
    t_rel = np.loadtxt(out / "trajectories" / f"{run}_trial0.tum", usecols=0, ndmin=1)
    scan_rel = np.asarray(rec.stamps) - rec.stamps[0]
    j = np.clip(np.searchsorted(scan_rel, t_rel), 1, len(scan_rel) - 1)
    j = np.where(np.abs(scan_rel[j - 1] - t_rel) <= np.abs(scan_rel[j] - t_rel), j - 1, j)
    if len(t_rel) != n_steps or np.max(np.abs(scan_rel[j] - t_rel)) > 1e-3:
        raise RuntimeError(f"{out}: {n_steps} steps for {len(rec.gt)} scans, and their stamps do not match the scans'")
    return j


def truth_errors(out: Path, rec, map_from_grid=None) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per trial: (position error m, heading error rad) per step against `rec.gt` (turned into the map frame by
    `map_from_grid` when the map.yaml's origin turns the grid)."""
    from pipeline.runtime.motion import compose2d

    est = read_estimates(out)
    truth = np.asarray(rec.gt, dtype=np.float64)
    if map_from_grid is not None:
        truth = compose2d(np.repeat(np.asarray([map_from_grid], np.float64), len(truth), 0), truth)
    out_errs = {}
    for trial, e in est.groupby("trial"):
        e = e.sort_values("step")
        idx = steps_to_scans(out, str(e["run"].iloc[0]), len(e), rec)
        g = truth[idx]
        err = np.hypot(e["x"].to_numpy() - g[:, 0], e["y"].to_numpy() - g[:, 1])
        err_t = np.abs(wrap(e["theta"].to_numpy() - g[:, 2]))
        out_errs[int(trial)] = (err, err_t)
    return out_errs


def replay(cfg, bag: Path, map_yaml: Path, out: Path, init: str, start_pose=None, trials: int = 1,
           write_bag: Path | None = None) -> tuple[Path, float]:
    from pipeline.rosbag.replay import run_localize_bag

    t0 = time.perf_counter()
    res = run_localize_bag(cfg, inputs={"bag": bag, "map": map_yaml}, outputs={"out": out}, init=init,
                           start_pose=None if start_pose is None else tuple(float(v) for v in start_pose),
                           trials=trials, write_bag=write_bag, force=True, progress=False)
    return res, time.perf_counter() - t0


def fmt(v, f="{:.3f}"):
    return "-" if v is None else f.format(v)


# --------------------------------------------------------------------------------------------- traits


def run_traits(cfg, work: Path, names: list[str] | None) -> None:
    from pipeline.runtime.motion import compose2d

    cases = [c for c in CASES if not names or c.name in names or slug(c.name) in names]
    rows = []
    for case in cases:
        folder = work / "traits" / slug(case.name)
        if folder.exists():
            shutil.rmtree(folder)
        o = case.map_opts
        res = o.get("res", 0.05)
        occ = rr.floor_map(res, pad_m=o.get("pad", 0.0))
        world = rr.floor_map(o["world_res"], pad_m=o.get("pad", 0.0)) if "world_res" in o else occ
        t0 = time.perf_counter()
        try:
            rec = rr.record(bag_path(folder, case.traits), world, case.traits)
            map_yaml = rr.write_map_yaml(folder / "map.yaml", occ, mode=o.get("mode", "trinary"),
                                         negate=o.get("negate", 0), origin=o.get("origin"))
            turn = o.get("origin")  # map_from_grid: the floor's grid has its origin at (0, 0, 0) (no pad)
            start = rec.gt[0] if turn is None else compose2d(np.asarray([turn]), rec.gt[:1])[0]
            out, wall = replay(cfg, rec.path, map_yaml, folder / "out", "pose", start_pose=start)
            err, err_t = truth_errors(out, rec, turn)[0]
            doc = json.loads((out / "metrics.json").read_text())
            m = next(iter(doc["runs"].values()))[0]
            rows.append((case.name, len(rec.gt), len(err), float(np.median(err)), float(np.percentile(err, 90)),
                         math.degrees(float(np.median(err_t))), m.get("error_median_m"), m["quality"]["converged"],
                         doc.get("notes", []), wall))
        except Exception as exc:  # noqa: BLE001 - a case that fails is a finding, reported in the table
            rows.append((case.name, None, None, None, None, None, None, None, [f"FAILED: {type(exc).__name__}: "
                                                                                f"{exc}"], time.perf_counter() - t0))
        r = rows[-1]
        print(f"{case.name:36s} median {fmt(r[3])} m  p90 {fmt(r[4])} m  ({r[9]:.1f} s)"
              + (f"  {r[8][0][:200]}" if r[3] is None else ""), flush=True)
    ok = sum(1 for r in rows if r[3] is not None and r[3] <= TARGET_M)
    print(f"\n### Every trait from --init pose (whole default drive, filter.seed 3): {ok}/{len(rows)} within "
          f"{TARGET_M} m median\n")
    print("| case | scans | steps | median error (m) | p90 error (m) | median <= 0.05 m | median heading error (deg) "
          "| metrics.json error_median_m (bag reference) | quality rule converged | replay s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, scans, steps, med, p90, head, ref, qc, notes, wall in rows:
        if med is None:
            print(f"| {name} | - | - | {notes[0]} | | | | | | {wall:.1f} |")
            continue
        print(f"| {name} | {scans} | {steps} | {med:.4f} | {p90:.4f} | {'yes' if med <= TARGET_M else '**no**'} | "
              f"{head:.2f} | {fmt(ref, '{:.4f}')} | {qc} | {wall:.1f} |")
    notes = [(r[0], n) for r in rows if r[3] is not None for n in r[8]]
    if notes:
        print("\nNotes the replays wrote (metrics.json):")
        for name, n in notes:
            print(f"- {name}: {n}")


# --------------------------------------------------------------------------------------------- office


def office_map():
    """The office reference site's occupancy map (its preset and seed 0; the plan rasterised, no rendering)
    and its capture stops (free space reachable from the corridors)."""
    from pipeline.sitegen.laser import rasterise_map
    from pipeline.sitegen.presets import load_site_preset
    from pipeline.sitegen.site_scene import build_scene
    from pipeline.sitegen.trajectories import sample_stops

    preset = load_site_preset("office")
    scene = build_scene(preset, 0, False)
    occ = rasterise_map(scene, preset.map_resolution)
    stops = sample_stops(scene, occ, spacing=preset.stops.spacing, clearance=preset.stops.clearance,
                         jitter=preset.stops.jitter, seed=0)
    return occ, np.asarray([s[:2] for s in stops])


def office_waypoints(occ, stops: np.ndarray, n: int, seed: int = 0) -> list[tuple[float, float]]:
    """A drive through `n` random capture stops in nearest-neighbour order, each leg the shortest path with
    0.3 m clearance (`pipeline.sitegen.routes.RoutePlanner`; doors are 0.95 m wide), stops it cannot reach left out."""
    from pipeline.sitegen.routes import RoutePlanner

    planner = RoutePlanner(occ, clearance=0.3)
    rng = np.random.default_rng(seed)
    stops = stops[rng.permutation(len(stops))]
    stops = [s for s in stops if planner.is_clear(*s) and planner.connected(tuple(stops[0]), tuple(s))]
    pick = np.asarray(stops[:n])
    order, left = [0], list(range(1, len(pick)))
    while left:
        here = pick[order[-1]]
        k = min(left, key=lambda i: float(np.hypot(*(pick[i] - here))))
        order.append(k)
        left.remove(k)
    pts = [tuple(map(float, pick[order[0]]))]
    for a, b in zip(order[:-1], order[1:], strict=True):
        leg = planner.leg(tuple(pick[a]), tuple(pick[b]))
        pts.extend(tuple(map(float, p)) for p in leg[1:])
    keep = [pts[0]]
    for p in pts[1:]:  # the fixture's drive divides by each leg's length: no repeated points
        if math.hypot(p[0] - keep[-1][0], p[1] - keep[-1][1]) > 1e-6:
            keep.append(p)
    return keep


def record_with_waypoints(waypoints, path: Path, occ, traits: Traits):
    """`record()` on a route of our own: it drives the fixture module's WAYPOINTS, so they are swapped for the
    call (a monkeypatch, restored after; the fixture itself is left as it is)."""
    saved = rr.WAYPOINTS
    rr.WAYPOINTS = list(waypoints)
    try:
        return rr.record(path, occ, traits)
    finally:
        rr.WAYPOINTS = saved


def run_office(cfg, work: Path, seeds: int, n_stops: int, seconds: float | None) -> None:
    from pipeline.evaluation.metrics import first_settled, replay_metrics

    folder = work / "office"
    if folder.exists():
        shutil.rmtree(folder)
    t0 = time.perf_counter()
    occ, stops = office_map()
    t_map = time.perf_counter() - t0
    wps = office_waypoints(occ, stops, n_stops)
    length = float(np.sum(np.hypot(*np.diff(np.asarray(wps), axis=0).T)))
    t0 = time.perf_counter()
    rec = record_with_waypoints(wps, folder / "rec", occ, Traits(reference=False, seconds=seconds))
    t_rec = time.perf_counter() - t0
    map_yaml = rr.write_map_yaml(folder / "map.yaml", occ)
    print(f"office map {occ.width} x {occ.height} cells at {occ.resolution} m ({occ.width * occ.resolution:.1f} x "
          f"{occ.height * occ.resolution:.1f} m), {len(stops)} stops, built in {t_map:.1f} s; route through "
          f"{n_stops} stops {length:.0f} m, {len(rec.gt)} scans ({rec.stamps[-1] - rec.stamps[0]:.0f} s), "
          f"recorded in {t_rec:.1f} s", flush=True)
    out, wall = replay(cfg, rec.path, map_yaml, folder / "out", "uniform", trials=seeds)
    errs = truth_errors(out, rec)
    doc = json.loads((out / "metrics.json").read_text())
    per_trial = {t["trial"]: t for t in next(iter(doc["runs"].values()))}
    est = read_estimates(out)
    seed0 = cfg.filter.seed
    print(f"\n### Uniform start on the office map: {seeds} seeds, laser only, no reference ({wall:.0f} s for all)\n")
    print("| seed | converged (held) | converged step | lost track at | median error after conv. (m) "
          "| p90 error after conv. (m) | quality rule converged | rule's converged step | true error there (m) "
          "| rule's lost steps | rule settled for good at | true error there (m) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    held = rule = 0
    for trial in sorted(errs):
        err, _ = errs[trial]
        e = est[est["trial"] == trial].sort_values("step")
        m = replay_metrics(err, [], e["particles"].to_numpy(), e["update_ms"].to_numpy(), e["updated"].to_numpy())
        q = per_trial[trial]["quality"]
        held += bool(m["held"])
        rule += bool(q["converged"])
        lost = ",".join(map(str, m["lost_track_steps"])) or "-"
        at_rule = None if q["converged_step"] is None else float(err[q["converged_step"]])
        # Where the rule settles after its last loss (its own test: agreement, spread, state for `hold` steps)
        rule_p = q["rule"]
        good = ((e["agreement"].astype(float).fillna(-1.0).to_numpy() >= rule_p["agreement"])
                & (e["spread_m"].to_numpy() <= rule_p["spread_m"]) & (e["state"].to_numpy() == "tracking"))
        last = q["lost_steps"][-1] if q["lost_steps"] else q["converged_step"]
        final = None if last is None else first_settled(np.where(good, 0.0, 1.0), last, 0.5, rule_p["hold"])
        print(f"| {seed0 + trial} | {'yes' if m['held'] else '**no**'} | {fmt(m['converged_step'], '{}')} | {lost} | "
              f"{fmt(m['error_median_m'])} | {fmt(m['error_p90_m'])} | {q['converged']} | "
              f"{fmt(q['converged_step'], '{}')} | {fmt(at_rule)} "
              f"| {','.join(map(str, q['lost_steps'])) or '-'} | {fmt(final, '{}')} "
              f"| {fmt(None if final is None else float(err[final]))} |")
    print(f"\nconverged and held: {held}/{len(errs)} (target >= {math.ceil(0.9 * len(errs))}); "
          f"quality rule says converged: {rule}/{len(errs)}")


# --------------------------------------------------------------------------------------------- long


def run_long(cfg_set: list[str], work: Path, minutes: list[float], write_bag_modes: list[str]) -> None:
    folder = work / "long"
    rows = []
    for mins in minutes:
        sub = folder / f"{mins:g}min"
        if sub.exists():
            shutil.rmtree(sub)
        loop = list(rr.WAYPOINTS)
        route = float(np.sum(np.hypot(*np.diff(np.asarray(loop + loop[:1]), axis=0).T)))
        loops = int(math.ceil(mins * 60 * rr.SPEED / route)) + 1
        t0 = time.perf_counter()
        # The default route is about 110 s long: it is driven round and round (the last waypoint back to the first)
        rec = record_with_waypoints(loop * loops, sub / "rec", rr.floor_map(), Traits(rate_hz=40.0, reference=False,
                                                                                      seconds=mins * 60.0))
        map_yaml = rr.write_map_yaml(sub / "map.yaml", rr.floor_map())
        duration = float(rec.stamps[-1] - rec.stamps[0])
        size = sum(p.stat().st_size for p in rec.path.rglob("*") if p.is_file())
        print(f"{mins:g} min: {len(rec.gt)} scans over {duration:.0f} s, {size / 1e6:.0f} MB, recorded in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        for mode in write_bag_modes:
            job = {"bag": str(rec.path), "map": str(map_yaml), "out": str(sub / f"out_{mode}"),
                   "pose": [float(v) for v in rec.gt[0]], "set": cfg_set,
                   "write_bag": str(sub / "replay.mcap") if mode == "yes" else None}
            env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
            p = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)], env=env, capture_output=True,
                               text=True)
            if p.returncode != 0:
                print(f"  write-bag {mode}: FAILED\n{p.stderr[-3000:]}", flush=True)
                rows.append((mins, len(rec.gt), duration, mode, None))
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            rows.append((mins, len(rec.gt), duration, mode, r))
            print(f"  write-bag {mode}: {r['wall_s']:.1f} s, peak RSS {r['maxrss_mb']:.0f} MB (CPUs {r['affinity']}, "
                  f"threads {r['threads']})", flush=True)
            if mode == "yes":
                (sub / "replay.mcap").unlink(missing_ok=True)
    print("\n### Long 40 Hz laser-only recordings, --init pose, one core (CPU 0, one thread)\n")
    print("| minutes | scans | recording s | write-bag | replay wall s | ratio to real time | peak RSS MB "
          "| RSS after imports MB | replay bag MB | steps updated | ms / update |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for mins, scans, duration, mode, r in rows:
        if r is None:
            print(f"| {mins:g} | {scans} | {duration:.0f} | {mode} | FAILED | | | | | | |")
            continue
        print(f"| {mins:g} | {scans} | {duration:.0f} | {mode} | {r['wall_s']:.1f} | {r['wall_s'] / duration:.3f} | "
              f"{r['maxrss_mb']:.0f} | {r['rss_imports_mb']:.0f} | {fmt(r['bag_mb'], '{:.0f}')} | {r['updated']} | "
              f"{fmt(r['update_ms'], '{:.2f}')} |")


def peak_rss_mb() -> float:
    """This process's peak resident set (VmHWM; Linux). Not getrusage's ru_maxrss: Linux carries that across
    fork and exec, so a child would report its parent's peak (here the parent holding a recording it wrote)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child(job: dict) -> None:
    """One long replay in this process (threads already 1): prints a JSON line."""
    os.sched_setaffinity(0, {0})
    from pipeline.config import load_config
    from pipeline.rosbag.replay import run_localize_bag

    cfg = load_config("demo", ["filter.seed=3", *job["set"]])
    rss0 = peak_rss_mb()
    write_bag = Path(job["write_bag"]) if job["write_bag"] else None
    t0 = time.perf_counter()
    out = run_localize_bag(cfg, inputs={"bag": Path(job["bag"]), "map": Path(job["map"])},
                           outputs={"out": Path(job["out"])}, init="pose", start_pose=tuple(job["pose"]), trials=1,
                           write_bag=write_bag, force=True, progress=False)
    wall = time.perf_counter() - t0
    rss = peak_rss_mb()
    m = next(iter(json.loads((out / "metrics.json").read_text())["runs"].values()))[0]
    est = read_estimates(out)
    print(json.dumps({"wall_s": wall, "maxrss_mb": rss, "rss_imports_mb": rss0, "steps": m["steps"],
                      "updated": int(est["updated"].sum()), "update_ms": m.get("update_ms_mean"),
                      "bag_mb": write_bag.stat().st_size / 1e6 if write_bag else None,
                      "affinity": sorted(os.sched_getaffinity(0)),
                      "threads": ",".join(f"{v}={os.environ.get(v)}" for v in THREAD_VARS)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", nargs="*", default=list(PARTS), choices=PARTS)
    ap.add_argument("--work", type=Path, default=REPO / "data" / "robot_recordings",
                    help="where recordings and replays are written (each case's folder is replaced)")
    ap.add_argument("--cases", nargs="*", default=None, help="trait cases by name or slug (default: all)")
    ap.add_argument("--office-seeds", type=int, default=10)
    ap.add_argument("--office-stops", type=int, default=12, help="capture stops the office drive goes through")
    ap.add_argument("--office-seconds", type=float, default=None, help="cut the office drive (default: whole)")
    ap.add_argument("--long-minutes", type=float, nargs="*", default=[5.0, 10.0, 20.0])
    ap.add_argument("--long-write-bag", nargs="*", default=["no", "yes"], choices=["no", "yes"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (as --set)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(json.loads(args.child))
        return
    from benchmarks.mapping_benchmark import machine_info
    from pipeline.config import load_config

    print("\n".join(machine_info()))
    cfg = load_config("demo", ["filter.seed=3", *args.set])
    if args.set:
        print("overrides: " + ", ".join(args.set))
    if "traits" in args.parts:
        t0 = time.perf_counter()
        run_traits(cfg, args.work, args.cases)
        print(f"\n(traits: {time.perf_counter() - t0:.0f} s)", flush=True)
    if "office" in args.parts:
        t0 = time.perf_counter()
        run_office(cfg, args.work, args.office_seeds, args.office_stops, args.office_seconds)
        print(f"\n(office: {time.perf_counter() - t0:.0f} s)", flush=True)
    if "long" in args.parts:
        t0 = time.perf_counter()
        run_long(args.set, args.work, args.long_minutes, args.long_write_bag)
        print(f"\n(long: {time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
