"""Stage `localize`: replay recorded runs through the runtime filter and measure it.

Input: a dataset directory as `ingest` or `ingest-log` writes it (map.yaml + runs/<run>.parquet or .arrow, and
site.yaml for the laser mount when present). For each run and trial (trial t uses filter seed + t) the
filter starts as `init` says: `uniform` (global localization), `pose` (at the first ground-truth pose),
`candidates` (a simulated camera: at every step four ranked poses, the truth with noise among
free-space decoys, handed to the runtime's camera path, `pipeline.runtime.camera`), or `retrieval`:
the thin runtime of a deployable bundle (`Localizer.from_bundle`) with the runs' camera frames.
`kidnap_at` adds kidnappings by teleporting (`evaluation.replay.teleport`); runs that already flag
kidnappings keep theirs.

Writes `estimates.parquet` (per step), `metrics.json` (per run and trial, and a summary, with evo's APE
and RPE beside our own figures), the estimates and ground truth as TUM files in `trajectories/` (for
`evo_ape` / `evo_rpe`), figures in `plots/` and `config.yaml`.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, RuntimeInputError
from pipeline.io import tables
from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
from pipeline.io.map_yaml import read_map

INITS = ("uniform", "pose", "candidates", "retrieval")


def _mount(data: Path) -> tuple[float, float, float]:
    site_yaml = data / "site.yaml"
    if not site_yaml.is_file():
        return (0.0, 0.0, 0.0)
    from pipeline.io.site import read_site

    m = read_site(site_yaml).laser.mount
    return (m.x, m.y, float(np.radians(m.yaw_deg)))


def _run_paths(data: Path, names: list[str] | None) -> list[Path]:
    found = sorted([*(data / "runs").glob("*.parquet"), *(data / "runs").glob("*.arrow")])
    if not found:
        raise InputError(f"{data}: no runs", [Problem(str(data / "runs"), "no <run>.parquet or <run>.arrow files",
                                                      fix="point at the output of `siteloc ingest` or `ingest-log`")])
    if names:
        by_name = {p.stem: p for p in found}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise InputError(f"{data}: unknown runs {missing}",
                             [Problem(str(data / "runs"), f"run '{n}' not found", fix=f"one of {sorted(by_name)}")
                              for n in missing])
        return [by_name[n] for n in names]
    return found


def _at_step(run, t: int, err: RuntimeInputError, what: str = "") -> RuntimeInputError:
    """The runtime's refusal of a run's input, naming the run and the step."""
    return RuntimeInputError(f"run {run.name}, step {t} of {len(run)}{what}: {err}")


def replay_one(run, lmap, fcfg, mount, init: str, trial: int, candidate_weights=None, start_pose=None,
               keep_cloud: int = 0, on_step=None) -> dict:
    """Replay `run` once; returns per-step arrays and the final particle set. With `candidates`, a
    simulated camera proposes len(candidate_weights) ranked poses at every step and the runtime's camera
    path (`CameraPath`) uses them as retrieval's, weighted `candidate_weights` (retrieval.candidate_weights).
    `pose` starts at `start_pose` (else the first ground-truth pose); `keep_cloud` particles per step are
    kept (`cloud`) for the replay bag; `on_step(t, pose, covariance, state, particles)` sees each step (the
    particles where the filter updated, else None)."""
    from pipeline.evaluation.replay import simulated_candidates
    from pipeline.runtime import inputs
    from pipeline.runtime.amcl import AdaptiveMCL
    from pipeline.runtime.camera import CameraPath
    from pipeline.runtime.sensor import Scan

    cfg = fcfg.model_copy(update={"seed": fcfg.seed + trial})
    f = AdaptiveMCL(lmap, cfg, range_max=run.range_max, base_from_laser=mount)
    rng = np.random.default_rng(cfg.seed + 7_777)
    if init == "candidates" and not candidate_weights:
        raise ValueError("init 'candidates' needs candidate_weights (retrieval.candidate_weights)")
    n_cand = len(candidate_weights or ())
    camera = None
    if init == "pose":
        try:
            f.init_pose(run.gt[0] if start_pose is None else start_pose)
        except RuntimeInputError as err:
            what = " (its ground-truth pose, --init pose)" if start_pose is None else " (--pose)"
            raise _at_step(run, 0, err, what) from None
    elif init == "candidates":
        # The camera's ranked poses at step t: the truth with noise among free-space decoys, at a random rank.
        camera = CameraPath(f, cfg, candidate_weights, range_max=run.range_max, base_from_laser=mount,
                            rank_image=lambda t: simulated_candidates(run.gt[t], lmap, n_cand, rng))
    else:
        f.init_uniform()
    def scan(t: int) -> Scan:  # one at a time: a long run's ranges are read as the replay reaches them
        return Scan(run.ranges[t], run.angle_min, run.angle_increment, run.range_max)

    f.sensor.evaluate(f.particles[:2], scan(0))  # compile the kernels before timing anything
    if camera is not None:
        camera.verifier  # noqa: B018 - its range table is built before timing anything
    T, beams = len(run), len(run.ranges[0])
    out = _step_arrays(T)
    odom = None
    for t in range(T):
        try:  # what the bundle's Localizer checks (its update); the run's own laser sets the beam count
            odom = inputs.odometry(run.odom[t], odom)
            inputs.ranges(run.ranges[t], beams, run.angle_increment)
        except RuntimeInputError as err:
            raise _at_step(run, t, err) from None
        t0 = time.perf_counter()
        res = f.update(run.odom[t], scan(t)) if camera is None else camera.step(run.odom[t], scan(t), t).result
        ms = (time.perf_counter() - t0) * 1000.0
        _put(out, t, res.pose, res.covariance, res.state.value, res.particles, res.updated, res.best_likelihood, ms)
        out["cloud"].append(cloud_of(f.particles, keep_cloud) if res.updated or t == 0 else None)
        if on_step is not None:
            on_step(t, res.pose, res.covariance, res.state.value, f.particles if res.updated or t == 0 else None)
    out["final_particles"] = f.particles.copy()
    return out


def _step_arrays(n: int) -> dict:
    """A replay's per-step outputs, allocated once (no Python object per step and field)."""
    return {"pose": np.zeros((n, 3)), "cov": np.zeros((n, 3, 3)), "state": [], "particles": np.zeros(n, np.int64),
            "updated": np.zeros(n, bool), "best": np.zeros(n), "ms": np.zeros(n), "cloud": []}


def _put(out: dict, t: int, pose, cov, state: str, particles: int, updated: bool, best, ms: float) -> None:
    out["pose"][t], out["cov"][t], out["particles"][t], out["updated"][t] = pose, cov, particles, updated
    out["best"][t] = np.nan if best is None else best
    out["ms"][t] = ms
    out["state"].append(state)


def cloud_of(particles: np.ndarray, n: int) -> np.ndarray | None:
    """At most n particles, evenly strided (float32), for the replay bag; None when n is 0. Kept only where the
    filter updated (the set is the same in between)."""
    if n <= 0:
        return None
    step = max(1, len(particles) // n)
    return particles[::step][:n].astype(np.float32)


def replay_bundle(run, loc, data: Path, trial: int, keep_cloud: int = 0, on_step=None) -> dict:
    """Replay `run` through a bundle's Localizer with the run's camera frames (in `data`), if it has any:
    without, the bundle's filter runs on the laser alone. Scans keep the run's own laser geometry."""
    from pipeline.runtime.sensor import Scan

    loc.reset(seed=loc.base_seed + trial)  # trial t: seed + t, whatever was replayed before
    out = {**_step_arrays(len(run)), "candidates": []}
    seeded = None  # the candidates the filter started from (x, y, theta, weight)
    images = run.image_ids or (None,) * len(run)
    for t in range(len(run)):
        image = data / images[t] if images[t] else None
        scan = Scan(run.ranges[t], run.angle_min, run.angle_increment, run.range_max)
        t0 = time.perf_counter()
        try:
            e = loc.update(run.odom[t], scan, image=image)
        except RuntimeInputError as err:
            raise _at_step(run, t, err) from None
        ms = (time.perf_counter() - t0) * 1000.0
        if seeded is None and e.candidates is not None:
            seeded = e.candidates
        _put(out, t, e.pose, e.covariance, e.state, e.n_particles, e.updated, e.best_likelihood, ms)
        out["candidates"].append(e.candidates)
        out["cloud"].append(cloud_of(loc.filter.particles, keep_cloud) if e.updated or t == 0 else None)
        if on_step is not None:
            on_step(t, e.pose, e.covariance, e.state, loc.filter.particles if e.updated or t == 0 else None)
    out["final_particles"] = loc.filter.particles.copy()
    out["seed_candidates"] = seeded
    return out


def estimate_columns(run, trial: int, rep: dict, err: np.ndarray, err_t: np.ndarray) -> dict:
    """The columns of an `estimates` table for one replay (`replay_one` / `replay_bundle` output, with the
    quality of `quality_of`)."""
    import pyarrow as pa

    from pipeline.runtime.quality import spread_m

    n = len(run)
    pose = rep["pose"]
    gt = run.gt if run.gt is not None else np.full((n, 3), np.nan)
    agreement = rep.get("agreement")  # None: not computed (`siteloc evaluate`'s replays, measured against truth)
    return {"run": [run.name] * n, "trial": [trial] * n, "step": np.arange(n), "x": pose[:, 0], "y": pose[:, 1],
            "theta": pose[:, 2], "cov_xx": rep["cov"][:, 0, 0], "cov_xy": rep["cov"][:, 0, 1],
            "cov_yy": rep["cov"][:, 1, 1], "cov_tt": rep["cov"][:, 2, 2], "state": rep["state"],
            "particles": rep["particles"], "updated": rep["updated"], "best_likelihood": rep["best"],
            "update_ms": rep["ms"],
            # NaN (no usable beam) and "not computed" are nulls; an Arrow array, not a Python float per step
            "agreement": pa.nulls(n, pa.float64()) if agreement is None else pa.array(np.asarray(agreement, np.float64),
                                                                                      from_pandas=True),
            "spread_m": rep["spread"] if "spread" in rep else spread_m(rep["cov"][:, 0, 0], rep["cov"][:, 0, 1],
                                                                       rep["cov"][:, 1, 1]),
            "gt_x": gt[:, 0], "gt_y": gt[:, 1], "gt_theta": gt[:, 2],
            "error_xy": err, "error_theta": err_t, "kidnapped": run.kidnapped}


def quality_of(rep: dict, run, lmap, mount, cfg: SitelocConfig) -> dict:
    """What the robot itself can tell of a replay (`pipeline.runtime.quality`): per step the share of beams the
    map explains at the estimate and the particle spread (added to `rep`), per run the rule's verdict."""
    from pipeline.runtime import quality

    rule = quality.QualityRule()
    rep["agreement"] = quality.beam_agreement(lmap, rep["pose"], run.ranges, run.angle_min, run.angle_increment,
                                              run.range_max, mount, rule.tolerance_m,
                                              range_min=cfg.filter.sensor.range_min)
    rep["spread"] = quality.spread_m(rep["cov"][:, 0, 0], rep["cov"][:, 0, 1], rep["cov"][:, 1, 1])
    verdict = quality.assess(rep["agreement"], rep["spread"], rep["state"], rule, kidnapped=run.kidnapped,
                             updated=rep["updated"])
    verdict.pop("good_steps")
    return verdict


def run_localize(
    cfg: SitelocConfig,
    *,
    inputs: dict[str, Path],
    outputs: dict[str, Path],
    runs: list[str] | None = None,
    init: str = "uniform",
    trials: int = 1,
    kidnap_at: list[int] | None = None,
    kidnap_min_jump_m: float = 10.0,
    bundle: Path | None = None,
    start_pose: tuple[float, float, float] | None = None,
    force: bool = False,
    progress: bool = True,
    keep_cloud: int = 0,
    on_replay=None,
    on_step=None,
) -> Path:
    """`start_pose` (map frame, radians) starts `pose` there instead of at the ground truth. `on_replay(run,
    rep, tmp)` is called with trial 0 of each run (poses in the map frame, `cloud`: `keep_cloud` particles per
    step) while the output is being written in `tmp`. `on_step(run, t, pose, state, particles, agreement,
    spread)` sees each step of trial 0 as it is computed (map frame; `pipeline.rosbag.live`)."""
    from pipeline.evaluation import plots
    from pipeline.evaluation.map_frame import grid_frame, turned, turned_cov, with_gt
    from pipeline.evaluation.metrics import replay_metrics
    from pipeline.evaluation.overview import overview_figure
    from pipeline.evaluation.replay import load_run, teleport
    from pipeline.evaluation.trajectories import evo_metrics, step_stamps, write_tum
    from pipeline.progress import progress_bar
    from pipeline.runtime.grid import LaserMap
    from pipeline.runtime.motion import wrap_angle

    if init not in INITS:
        raise ValueError(f"init must be one of {INITS}, got '{init}'")
    from pipeline.errors import ConfigError

    if (init == "retrieval") != (bundle is not None):
        raise ConfigError("--init retrieval and --bundle go together: the bundle's detector and database "
                          "turn the runs' camera frames into candidate poses")
    if start_pose is not None and init != "pose":
        raise ConfigError("--pose goes with --init pose")
    check_output(Path(outputs["out"]), force=force, inputs=[*inputs.values(), bundle])
    loc = None
    if bundle is not None:
        from pipeline.runtime.localizer import Localizer

        loc = Localizer.from_bundle(Path(bundle), seed=cfg.filter.seed)
    data, out = Path(inputs["data"]), Path(outputs["out"])
    occ_map = read_map(data / "map.yaml")
    occ, map_from_grid = grid_frame(occ_map)
    lmap = LaserMap.from_occupancy(occ, cfg.filter.sensor.max_distance)
    mount = _mount(data)
    paths = _run_paths(data, runs)
    loaded = [load_run(p) for p in paths]
    notes = []
    for r in loaded:
        if r.gt is None and ((init != "uniform" and start_pose is None and init != "retrieval") or kidnap_at):
            raise InputError(f"{r.name}: no ground truth", [Problem(
                r.name, f"--init {init} and kidnappings need it", fix="use --init uniform without --kidnap-at, "
                "or --init pose --pose X,Y,THETA to start at a pose you know")])
        start = None if r.gt is None else turned(map_from_grid, r.gt[:1], inverse=True)[0]
        if start is not None and not lmap.known(start[0], start[1]):
            where = "off the map" if lmap.cell_of(start[0], start[1]) is None else "in unknown space"
            raise InputError(f"{r.name}: the recording starts outside the map", [Problem(
                r.name, f"its reference puts the robot at ({r.gt[0, 0]:.2f}, {r.gt[0, 1]:.2f}) m at the first step, "
                f"{where}", fix="use the map of the place the robot drove in (its map.yaml and origin), or cut the "
                "recording where the robot enters the map")])
        if loc is not None and not any(r.image_ids or ()):
            notes.append(f"{r.name}: no camera frames; the bundle's filter runs on the laser alone")
    grid_start = None if start_pose is None else turned(map_from_grid, np.asarray([start_pose]), inverse=True)[0]
    parts: list[dict] = []  # per replay, the estimates' columns (arrays: no Python object per step and column)
    per_run: dict[str, list[dict]] = {}
    with atomic_dir(out, force=force, inputs=[*inputs.values(), bundle]) as tmp:
        jobs = [(r, t) for r in loaded for t in range(trials)]
        for run, trial in progress_bar(jobs, desc="replaying", unit="replay", enabled=progress):
            if kidnap_at:
                run = teleport(run, kidnap_at, kidnap_min_jump_m, seed=cfg.filter.seed + 1000 * trial)
            grid_run = run if map_from_grid is None else with_gt(run, turned(map_from_grid, run.gt, inverse=True))
            hook = _step_hook(on_step, run, grid_run, lmap, mount, map_from_grid, cfg) if trial == 0 else None
            rep = (replay_bundle(grid_run, loc, data, trial, keep_cloud, on_step=hook) if loc is not None
                   else replay_one(grid_run, lmap, cfg.filter, mount, init, trial,
                                     candidate_weights=cfg.retrieval.candidate_weights, start_pose=grid_start,
                                     keep_cloud=keep_cloud, on_step=hook))
            quality = quality_of(rep, grid_run, lmap, mount, cfg)
            grid_pose = rep["pose"]
            rep["pose"] = pose = turned(map_from_grid, grid_pose)
            rep["cov"] = turned_cov(map_from_grid, rep["cov"])
            kid = np.nonzero(run.kidnapped)[0].tolist()
            stamps = step_stamps(run.t, len(run))
            write_tum(tmp / "trajectories" / f"{run.name}_trial{trial}.tum", pose, stamps)
            if run.gt is not None:
                err = np.hypot(*(pose[:, :2] - run.gt[:, :2]).T)
                err_t = np.abs(wrap_angle(pose[:, 2] - run.gt[:, 2]))
                m = replay_metrics(err, [k for k in kid if k > 0], rep["particles"], rep["ms"], rep["updated"])
                m["evo"] = evo_metrics(pose, run.gt, stamps)
                if trial == 0 or kidnap_at:  # teleported runs differ by trial
                    name = f"{run.name}_groundtruth" + (f"_trial{trial}" if kidnap_at else "")
                    write_tum(tmp / "trajectories" / f"{name}.tum", run.gt, stamps)
            else:
                err = err_t = np.full(len(run), np.nan)
                ms = rep["ms"][rep["updated"]]
                m = {"steps": len(run), "update_ms_mean": round(float(np.mean(ms)), 4) if len(ms) else None}
            m["quality"] = quality
            per_run.setdefault(run.name, []).append({"trial": trial, **m})
            parts.append(estimate_columns(run, trial, rep, err, err_t))
            if trial == 0:
                title = f"{run.name}: init {init}, {cfg.filter.method}, {cfg.filter.sensor.model}"
                if run.gt is not None:
                    plots.replay_figure(tmp / "plots" / f"{run.name}_error.png", title, err, rep["state"],
                                        rep["particles"], kid)
                plots.trajectory_figure(tmp / "plots" / f"{run.name}_map.png", occ, grid_run.gt, grid_pose,
                                        rep["final_particles"], title)
                conv = m.get("converged_step") if run.gt is not None else quality["converged_step"]
                lost = m.get("lost_track_steps", []) if run.gt is not None else quality["lost_steps"]
                overview_figure(tmp / "plots" / f"{run.name}_overview.png", occ, grid_pose, rep["state"],
                                gt=grid_run.gt, converged_step=conv, lost_steps=lost, kidnapped_steps=kid,
                                title=f"{title}" + ("" if run.gt is not None else " (no reference: quality rule)"))
                if on_replay is not None:
                    on_replay(run, rep, tmp)
        write_estimates(tmp / "estimates.parquet", parts, {"init": init, "method": cfg.filter.method})
        errs = {name: np.concatenate([p["error_xy"] for p in parts if p["run"][0] == name]) for name in per_run}
        if any(np.isfinite(e).any() for e in errs.values()):
            plots.error_cdf_figure(tmp / "plots" / "error_cdf.png", {k: e[np.isfinite(e)] for k, e in errs.items()})
        summary = _summary(per_run)
        doc = {"init": init, "method": cfg.filter.method, "sensor_model": cfg.filter.sensor.model,
               "candidates": ("simulated from ground truth: the true pose (0.5 m, 10 deg noise) among random "
                              "free-space decoys, random rank, every step, through the camera path")
               if init == "candidates" else
               (f"image retrieval with the bundle {bundle}" if loc is not None else None),
               "start_pose": None if start_pose is None else [float(v) for v in start_pose],
               "trials": trials, "kidnap_at": kidnap_at or [], "notes": notes, "summary": summary, "runs": per_run}
        write_text_atomic(tmp / "metrics.json", json.dumps(doc, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="localize", inputs={"data": data})
    return out


#: Rows per row group of estimates.parquet.
ESTIMATE_ROWS = 8192


def write_estimates(path: Path, parts: list[dict], metadata: dict[str, str]) -> Path:
    """An `estimates` table from the columns of several replays (`estimate_columns`), a row group of at most
    ESTIMATE_ROWS steps at a time: a long replay's table is never built whole."""

    def chunks():
        for columns in parts:
            n = len(columns["step"])
            for a in range(0, max(n, 1), ESTIMATE_ROWS):
                yield tables.to_table("estimates", {k: v[a: a + ESTIMATE_ROWS] for k, v in columns.items()})

    tables.write_table_parts(path, chunks(), "estimates", metadata=metadata)
    return Path(path)


def _step_hook(on_step, run, grid_run, lmap, mount, map_from_grid, cfg):
    """`on_step` fed in the map frame, with the step's agreement and spread (as `quality_of` computes them)."""
    if on_step is None:
        return None
    from pipeline.evaluation.map_frame import turned
    from pipeline.runtime import quality

    rule = quality.QualityRule()

    def hook(t, pose, cov, state, particles):
        agree = quality.beam_agreement(lmap, np.asarray(pose)[None], grid_run.ranges[t: t + 1], run.angle_min,
                                       run.angle_increment, run.range_max, mount, rule.tolerance_m,
                                       range_min=cfg.filter.sensor.range_min)[0]
        spread = float(quality.spread_m(cov[0, 0], cov[0, 1], cov[1, 1]))
        on_step(run, t, turned(map_from_grid, np.asarray(pose)[None])[0], state,
                None if particles is None else turned(map_from_grid, cloud_of(particles, LIVE_CLOUD)),
                float(agree), spread)

    return hook


#: Particles per step a live view shows.
LIVE_CLOUD = 500


def _summary(per_run: dict[str, list[dict]]) -> dict:
    """Per run over its trials. `converged` counts the trials that converged and never lost track (a
    filter that converges and then walks away is counted in `lost_track`, with its steps per trial)."""
    out = {}
    for name, trials in per_run.items():
        if "converged_step" not in trials[0]:
            out[name] = {"trials": len(trials)}
            continue
        conv = [t["converged_step"] for t in trials if t["converged_step"] is not None]
        rec = [r for t in trials for r in t["recovery_steps"]]
        ok = [r for r in rec if r is not None]

        def median_of(get, trials=trials):
            v = [x for trial in trials if (x := get(trial)) is not None]
            return float(np.median(v)) if v else None

        def median(key):
            return median_of(lambda trial: trial[key])

        out[name] = {
            "trials": len(trials),
            "converged": sum(t["held"] for t in trials),
            "lost_track": sum(bool(t["lost_track_steps"]) for t in trials),
            "lost_track_steps": [t["lost_track_steps"] for t in trials],
            "converged_step_median": float(np.median(conv)) if conv else None,
            "within_threshold_share_median": median("within_threshold_share"),
            "error_median_m": median("error_median_m"),
            "error_median_all_m": median("error_median_all_m"),
            "kidnaps": len(rec),
            "recovered": len(ok),
            "recovery_steps_median": float(np.median(ok)) if ok else None,
            "ape_rmse_m_median": median_of(lambda t: (t["evo"]["ape_m"] or {}).get("rmse")),
            "rpe_rmse_m_median": median_of(lambda t: (t["evo"]["rpe_m"] or {}).get("rmse")),
            "update_ms_mean": float(np.mean(ms)) if (ms := [t["update_ms_mean"] for t in trials
                                                            if t["update_ms_mean"] is not None]) else None,
        }
    return out
