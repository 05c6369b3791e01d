"""Stage `localize`: replay recorded runs through the runtime filter and measure it.

Input: a dataset directory as `ingest` or `ingest-log` writes it (map.yaml + runs/<run>.parquet, and
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
    found = sorted((data / "runs").glob("*.parquet"))
    if not found:
        raise InputError(f"{data}: no runs", [Problem(str(data / "runs"), "no <run>.parquet files",
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


def replay_one(run, lmap, fcfg, mount, init: str, trial: int, candidate_weights=None) -> dict:
    """Replay `run` once; returns per-step arrays and the final particle set. With `candidates`, a
    simulated camera proposes len(candidate_weights) ranked poses at every step and the runtime's camera
    path (`CameraPath`) uses them as retrieval's, weighted `candidate_weights` (retrieval.candidate_weights)."""
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
            f.init_pose(run.gt[0])
        except RuntimeInputError as err:
            raise _at_step(run, 0, err, " (its ground-truth pose, --init pose)") from None
    elif init == "candidates":
        # The camera's ranked poses at step t: the truth with noise among free-space decoys, at a random rank.
        camera = CameraPath(f, cfg, candidate_weights, range_max=run.range_max, base_from_laser=mount,
                            rank_image=lambda t: simulated_candidates(run.gt[t], lmap, n_cand, rng))
    else:
        f.init_uniform()
    scans = [Scan(r, run.angle_min, run.angle_increment, run.range_max) for r in run.ranges]
    f.sensor.evaluate(f.particles[:2], scans[0])  # compile the kernels before timing anything
    if camera is not None:
        camera.verifier  # noqa: B018 - its range table is built before timing anything
    T = len(run)
    out = {k: [] for k in ("pose", "cov", "state", "particles", "updated", "best", "ms")}
    odom = None
    for t in range(T):
        try:  # what the bundle's Localizer checks (its update); the run's own laser sets the beam count
            odom = inputs.odometry(run.odom[t], odom)
            inputs.ranges(run.ranges[t], len(run.ranges[0]), run.angle_increment)
        except RuntimeInputError as err:
            raise _at_step(run, t, err) from None
        t0 = time.perf_counter()
        res = f.update(run.odom[t], scans[t]) if camera is None else camera.step(run.odom[t], scans[t], t).result
        ms = (time.perf_counter() - t0) * 1000.0
        out["pose"].append(res.pose)
        out["cov"].append(res.covariance)
        out["state"].append(res.state.value)
        out["particles"].append(res.particles)
        out["updated"].append(res.updated)
        out["best"].append(res.best_likelihood)
        out["ms"].append(ms)
    out = {k: (v if k == "state" else np.array(v)) for k, v in out.items()}
    out["final_particles"] = f.particles.copy()
    return out


def replay_bundle(run, loc, data: Path, trial: int) -> dict:
    """Replay `run` through a bundle's Localizer with the run's camera frames (in `data`)."""
    if run.image_ids is None:
        raise InputError(f"{run.name}: no camera frames", [Problem(run.name, "--init retrieval needs image_id per step",
                                                                   fix="use a run recorded with a camera")])
    loc.reset(seed=loc.base_seed + trial)  # trial t: seed + t, whatever was replayed before
    out = {k: [] for k in ("pose", "cov", "state", "particles", "updated", "best", "ms")}
    seeded = None  # the candidates the filter started from (x, y, theta, weight)
    for t in range(len(run)):
        image = data / run.image_ids[t] if run.image_ids[t] else None
        t0 = time.perf_counter()
        try:
            e = loc.update(run.odom[t], run.ranges[t], image=image)
        except RuntimeInputError as err:
            raise _at_step(run, t, err) from None
        out["ms"].append((time.perf_counter() - t0) * 1000.0)
        if seeded is None and e.candidates is not None:
            seeded = e.candidates
        for key, value in (("pose", e.pose), ("cov", e.covariance), ("state", e.state), ("particles", e.n_particles),
                           ("updated", e.updated), ("best", e.best_likelihood)):
            out[key].append(value)
    out = {k: (v if k == "state" else np.array(v)) for k, v in out.items()}
    out["final_particles"] = loc.filter.particles.copy()
    out["seed_candidates"] = seeded
    return out


def estimate_columns(run, trial: int, rep: dict, err: np.ndarray, err_t: np.ndarray) -> dict:
    """The columns of an `estimates` table for one replay (`replay_one` / `replay_bundle` output)."""
    n = len(run)
    pose = rep["pose"]
    gt = run.gt if run.gt is not None else np.full((n, 3), np.nan)
    return {"run": [run.name] * n, "trial": [trial] * n, "step": np.arange(n), "x": pose[:, 0], "y": pose[:, 1],
            "theta": pose[:, 2], "cov_xx": rep["cov"][:, 0, 0], "cov_xy": rep["cov"][:, 0, 1],
            "cov_yy": rep["cov"][:, 1, 1], "cov_tt": rep["cov"][:, 2, 2], "state": rep["state"],
            "particles": rep["particles"], "updated": rep["updated"], "best_likelihood": rep["best"],
            "update_ms": rep["ms"], "gt_x": gt[:, 0], "gt_y": gt[:, 1], "gt_theta": gt[:, 2],
            "error_xy": err, "error_theta": err_t, "kidnapped": run.kidnapped}


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
    force: bool = False,
    progress: bool = True,
) -> Path:
    from pipeline.evaluation import plots
    from pipeline.evaluation.metrics import replay_metrics
    from pipeline.evaluation.replay import load_run, teleport
    from pipeline.evaluation.trajectories import evo_metrics, step_stamps, write_tum
    from pipeline.progress import progress_bar
    from pipeline.runtime.grid import LaserMap
    from pipeline.runtime.motion import wrap_angle

    if init not in INITS:
        raise ValueError(f"init must be one of {INITS}, got '{init}'")
    if (init == "retrieval") != (bundle is not None):
        from pipeline.errors import ConfigError

        raise ConfigError("--init retrieval and --bundle go together: the bundle's detector and database "
                          "turn the runs' camera frames into candidate poses")
    check_output(Path(outputs["out"]), force=force, inputs=[*inputs.values(), bundle])
    loc = None
    if bundle is not None:
        from pipeline.runtime.localizer import Localizer

        loc = Localizer.from_bundle(Path(bundle), seed=cfg.filter.seed)
    data, out = Path(inputs["data"]), Path(outputs["out"])
    occ = read_map(data / "map.yaml")
    lmap = LaserMap.from_occupancy(occ, cfg.filter.sensor.max_distance)
    mount = _mount(data)
    paths = _run_paths(data, runs)
    loaded = [load_run(p) for p in paths]
    for r in loaded:
        if r.gt is None and (init != "uniform" or kidnap_at):
            raise InputError(f"{r.name}: no ground truth", [Problem(r.name, f"--init {init} and kidnappings need it",
                                                                    fix="use --init uniform without --kidnap-at")])
    rows: dict[str, list] = {f.name: [] for f in tables.ESTIMATES}
    per_run: dict[str, list[dict]] = {}
    with atomic_dir(out, force=force, inputs=[*inputs.values(), bundle]) as tmp:
        jobs = [(r, t) for r in loaded for t in range(trials)]
        for run, trial in progress_bar(jobs, desc="replaying", unit="replay", enabled=progress):
            if kidnap_at:
                run = teleport(run, kidnap_at, kidnap_min_jump_m, seed=cfg.filter.seed + 1000 * trial)
            rep = (replay_bundle(run, loc, data, trial) if loc is not None
                   else replay_one(run, lmap, cfg.filter, mount, init, trial,
                                     candidate_weights=cfg.retrieval.candidate_weights))
            pose = rep["pose"]
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
            per_run.setdefault(run.name, []).append({"trial": trial, **m})
            for k, v in estimate_columns(run, trial, rep, err, err_t).items():
                rows[k].extend(list(v))
            if trial == 0:
                title = f"{run.name}: init {init}, {cfg.filter.method}, {cfg.filter.sensor.model}"
                if run.gt is not None:
                    plots.replay_figure(tmp / "plots" / f"{run.name}_error.png", title, err, rep["state"],
                                        rep["particles"], kid)
                plots.trajectory_figure(tmp / "plots" / f"{run.name}_map.png", occ, run.gt, pose,
                                        rep["final_particles"], title)
        tables.write_table(tmp / "estimates.parquet", tables.to_table("estimates", rows), "estimates",
                           metadata={"init": init, "method": cfg.filter.method})
        if any(v is not None for v in rows["error_xy"]):
            errs = np.array(rows["error_xy"], dtype=np.float64)
            run_col = np.array(rows["run"])
            plots.error_cdf_figure(tmp / "plots" / "error_cdf.png",
                                   {name: errs[(run_col == name) & np.isfinite(errs)] for name in per_run})
        summary = _summary(per_run)
        doc = {"init": init, "method": cfg.filter.method, "sensor_model": cfg.filter.sensor.model,
               "candidates": ("simulated from ground truth: the true pose (0.5 m, 10 deg noise) among random "
                              "free-space decoys, random rank, every step, through the camera path")
               if init == "candidates" else
               (f"image retrieval with the bundle {bundle}" if loc is not None else None),
               "trials": trials, "kidnap_at": kidnap_at or [], "summary": summary, "runs": per_run}
        write_text_atomic(tmp / "metrics.json", json.dumps(doc, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="localize", inputs={"data": data})
    return out


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
