"""The localization experiments of seed 000 section 4, run on a site's query runs from its bundle.

One deployable bundle (map, database, ONNX detector, filter settings) and the ingested site's query
runs (camera frame, odometry, laser scan and ground truth per step, kidnappings flagged) give every
method of the paper's figures the same inputs, seeds and filter settings (the bundle's filter.yaml):

- `proposed`: the bundle's Localizer as the robot runs it (its filter.yaml): the first frame's Top-4
  retrieved poses (4:3:2:1, checked against the scan) seed KLD-AMCL; the camera path
  (`pipeline.runtime.camera`) injects the current frame's (and, with a sequence model, the last `length`
  frames') best-fitting poses while the filter is not tracking, and weighs far hypotheses against a
  tracked belief.
- `image_reloc` and `sequence` (bundles with a sequence model): the same, re-localizing from the single
  image only, or from the sequence only (seed 000 section 3.3, the paper's Figure 12 "proposed").
- `amcl`: the same filter started uniform, no camera (Figure 8's "without image-based localization";
  augmented MCL's random particles are its only way back from a kidnapping).
- `mcl`: plain MCL with a fixed count (`max_particles`, the paper's 5000), uniform (Figure 9).
- `mixture`: mixture MCL (Thrun et al. 2001), uniform (Figure 10).
- `image_only`: no filter: each frame's Top-1 retrieved pose is the estimate (Figure 10).

Retrieval of a frame is deterministic (one ONNX pass, exact search), so each frame is described once
and its candidates are shared by `proposed`, `image_reloc`, `sequence` (every trial) and `image_only`; likewise each
frame's logits for the sequence LSTM are computed once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.evaluation.jobs import CachedRetrieval, PerImageCache, Replay, replay_job

METHODS = {
    "proposed": "retrieval Top-4 + KLD-AMCL (proposed)",
    "image_reloc": "... re-localized from single images only",
    "sequence": "... re-localized from image sequences only",
    "amcl": "KLD-AMCL, uniform start, no camera",
    "mcl": "MCL, fixed particle count, uniform start",
    "mixture": "mixture MCL, uniform start",
    "image_only": "image retrieval only (Top-1 pose per frame)",
}


def query_runs(data: Path, names: list[str] | None) -> list:
    """The runs to evaluate on: those named, else every `query_*` run; each needs ground truth and frames."""
    from pipeline.evaluation.replay import load_run

    runs_dir = Path(data) / "runs"
    paths = sorted(runs_dir.glob("query_*.parquet")) if not names else [runs_dir / f"{n}.parquet" for n in names]
    problems = [Problem(str(p), "no such run", fix=f"one of {sorted(q.stem for q in runs_dir.glob('*.parquet'))}")
                for p in paths if not p.is_file()]
    if not paths:
        problems.append(Problem(str(runs_dir), "no query_*.parquet runs",
                                fix="ingest a site with query runs (`siteloc synth` makes them), or name --run"))
    if problems:
        raise InputError(f"{data}: nothing to evaluate on", problems)
    runs = [load_run(p) for p in paths]
    for r in runs:
        if r.gt is None or r.image_ids is None or not any(r.image_ids):
            raise InputError(f"{r.name}: cannot be evaluated", [Problem(
                str(runs_dir / f"{r.name}.parquet"), "the experiments need ground truth and camera frames per step",
                fix="evaluate on runs recorded with a camera and ground truth (the reference site's query runs)")])
    return runs


def check_same_map(bundle_map, data: Path) -> None:
    """Refuse a site whose map frame is not the bundle's: its runs' poses would be measured in another frame.
    The cells may differ: the building may have changed since the bundle was exported (`siteloc check`)."""
    from pipeline.io.map_yaml import read_map

    path = Path(data) / "map.yaml"
    if not path.is_file():
        raise InputError(f"{data}: no map.yaml", [Problem(str(path), "missing",
                                                          fix="point DATA at the output of `siteloc ingest`")])
    occ = read_map(path)
    same = (occ.grid.shape == bundle_map.grid.shape
            and np.allclose([occ.resolution, occ.origin_x, occ.origin_y, occ.origin_yaw],
                            [bundle_map.resolution, bundle_map.origin_x, bundle_map.origin_y, bundle_map.origin_yaw]))
    if not same:
        raise InputError(f"{data}: not the site this bundle was exported for", [Problem(
            str(path), f"its map ({occ.width} x {occ.height} cells at {occ.resolution} m, origin {occ.origin_x}, "
            f"{occ.origin_y}) differs from the bundle's ({bundle_map.width} x {bundle_map.height} at "
            f"{bundle_map.resolution} m, origin {bundle_map.origin_x}, {bundle_map.origin_y})",
            fix="evaluate a bundle on the ingested site it was exported from")])


def run_experiments(loc, data: Path, runs: list, *, trials: int, threshold_m: float = 0.5, hold: int = 10,
                    progress: bool = True, methods: list[str] | None = None,
                    retrieve: CachedRetrieval | None = None,
                    workers: int | None = 1) -> tuple[dict[str, list[Replay]], CachedRetrieval]:
    """Every method (or those named) on every run and trial; returns {method: [Replay]} and the retrieval
    cache (pass it back as `retrieve` to replay other settings without describing the frames again).

    Every camera frame is described and retrieved first (in `workers` threads); `workers` > 1 (None: the
    usable cores, at most 8) then replays in that many processes (`pipeline.evaluation.parallel`); the
    replays are the same either way."""
    from pipeline.progress import progress_bar

    retrieve = retrieve or CachedRetrieval(loc)
    unknown = sorted(set(methods or ()) - set(METHODS))
    if unknown:
        raise ValueError(f"unknown methods {unknown}; known: {list(METHODS)}")
    methods = [m for m in METHODS if (m not in ("image_reloc", "sequence") or loc.sequence is not None)
               and (methods is None or m in methods)]
    jobs = [(m, i, t) for m in methods if m != "image_only" for i in range(len(runs)) for t in range(trials)]
    jobs += [("image_only", i, 0) for i in range(len(runs)) if "image_only" in methods]
    if workers is None:
        from pipeline.onnx_threads import thread_layout

        workers = thread_layout()[0]
    workers = max(1, min(workers, len(jobs)))
    from pipeline.evaluation.parallel import prefetch_retrievals, replay_in_processes

    # Up front, so that no method's update times include describing frames (each is described once for all).
    prefetch_retrievals(loc, data, runs, retrieve, threads=workers, progress=progress)
    if workers > 1:
        replays = replay_in_processes(loc, data, runs, jobs, retrieve, workers=workers, threshold_m=threshold_m,
                                      hold=hold, progress=progress)
    else:
        loc.retrieved = retrieve  # the Localizer calls self.retrieved: every trial shares the cache
        if loc.sequence is not None:
            loc.sequence.encode = PerImageCache(loc.sequence.encode)  # each frame's logits, once
        try:
            replays = [replay_job(loc, data, runs[i], method, trial, threshold_m, hold) for method, i, trial in
                       progress_bar(jobs, desc="experiments", unit="replay", enabled=progress)]
        finally:
            del loc.retrieved  # the class's own method again
            if loc.sequence is not None:
                del loc.sequence.encode
    out: dict[str, list[Replay]] = {m: [] for m in methods}
    for (method, _, _), replay in zip(jobs, replays, strict=True):
        out[method].append(replay)
    return out, retrieve


def summarise(replays: list[Replay]) -> dict:
    """One method over its replays: convergence (held, or lost track), accuracy, kidnap recovery, particles, time."""
    conv = [r.metrics["converged_step"] for r in replays if r.metrics["converged_step"] is not None]
    rec = [s for r in replays for s in r.metrics["recovery_steps"]]
    ok = [s for s in rec if s is not None]
    all_err = np.concatenate([r.errors for r in replays])
    global_err = np.concatenate([r.global_errors for r in replays])
    good = [r.metrics["error_mean_m"] for r in replays if r.metrics["error_mean_m"] is not None]
    med = [r.metrics["error_median_m"] for r in replays if r.metrics["error_median_m"] is not None]
    ms = [r.metrics["update_ms_mean"] for r in replays if r.metrics["update_ms_mean"] is not None]
    share = [r.metrics["within_threshold_share"] for r in replays if r.metrics["within_threshold_share"] is not None]

    def rnd(v, n=4):
        return None if v is None else round(float(v), n)

    return {
        "replays": len(replays),
        "converged": sum(r.metrics["held"] for r in replays),  # and never lost track afterwards
        "lost_track": sum(bool(r.metrics["lost_track_steps"]) for r in replays),
        "converged_step_median": rnd(np.median(conv)) if conv else None,
        "error_p90_global_m": rnd(np.percentile(global_err, 90)),
        "error_p90_all_m": rnd(np.percentile(all_err, 90)),
        "error_median_all_m": rnd(np.median(all_err)),
        "within_threshold_share_median": rnd(np.median(share)) if share else None,
        "ape_rmse_m_median": rnd(np.median(ape)) if (ape := [r.metrics["evo"]["ape_m"]["rmse"] for r in replays
                                                            if r.metrics.get("evo", {}).get("ape_m")]) else None,
        "error_mean_converged_m": rnd(np.mean(good)) if good else None,
        "error_median_converged_m": rnd(np.median(med)) if med else None,
        "kidnaps": len(rec),
        "recovered": len(ok),
        "recovery_steps_median": rnd(np.median(ok)) if ok else None,
        "recovery_steps_max": int(max(ok)) if ok else None,
        "recovered_within_15": int(sum(s <= 15 for s in ok)),
        "recovered_within_40": int(sum(s <= 40 for s in ok)),
        "particles_mean": rnd(np.mean(np.concatenate([r.particles for r in replays])), 1),
        "update_ms_mean": rnd(np.mean(ms), 3) if ms else None,
    }
