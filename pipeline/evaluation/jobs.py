"""One method's replay of one run: the unit of work `siteloc evaluate` runs, in this process or in a pool.

`replay_job` replays a run with a method of `experiments.METHODS` and measures it (`Replay`); the
caches make each frame's retrieval, a deterministic function of the image, run once per file.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Replay:
    """One method's replay of one run (one trial)."""

    run: str
    trial: int
    pose: np.ndarray  # (T, 3) estimates
    gt: np.ndarray  # (T, 3)
    errors: np.ndarray  # (T,) position error, m
    particles: np.ndarray  # (T,)
    kidnaps: list[int]
    metrics: dict
    rep: dict = field(repr=False, default_factory=dict)  # the raw replay (for the estimates table)

    @property
    def global_errors(self) -> np.ndarray:
        """Errors of the global localization: from the start to the first kidnapping (the paper's Figures 8-9
        measure global localization; kidnappings are Figures 11-12)."""
        return self.errors[: self.kidnaps[0]] if self.kidnaps else self.errors


class PerImageCache:
    """A deterministic function of an image file, computed once per file (`seconds`: each computation)."""

    def __init__(self, fn):
        self._fn = fn
        self.cache: dict[str, np.ndarray] = {}
        self.seconds: list[float] = []

    def __call__(self, image) -> np.ndarray:
        key = str(image)
        if key not in self.cache:
            t0 = time.perf_counter()
            self.cache[key] = self._fn(image)
            self.seconds.append(time.perf_counter() - t0)
        return self.cache[key]


class CachedRetrieval(PerImageCache):
    """A Localizer's `retrieved` poses (Top-N, best first), computed once per image file (deterministic;
    0.04-0.07 s each on 2 cores)."""

    def __init__(self, loc):
        super().__init__(loc.retrieved)


def measured(run, trial: int, rep: dict, threshold_m: float, hold: int) -> Replay:
    from pipeline.evaluation.metrics import replay_metrics
    from pipeline.evaluation.trajectories import evo_metrics, step_stamps

    err = np.hypot(*(rep["pose"][:, :2] - run.gt[:, :2]).T)
    kid = [int(k) for k in np.nonzero(run.kidnapped)[0] if k > 0]
    m = replay_metrics(err, kid, rep["particles"], rep["ms"], rep["updated"], threshold_m=threshold_m, hold=hold)
    replay = Replay(run.name, trial, rep["pose"], run.gt, err, np.asarray(rep["particles"]), kid, m, rep)
    m["error_p90_all_m"] = round(float(np.percentile(err, 90)), 4)
    m["error_p90_global_m"] = round(float(np.percentile(replay.global_errors, 90)), 4)
    m["evo"] = evo_metrics(rep["pose"], run.gt, step_stamps(run.t, len(run)))
    return replay


def image_only_replay(run, data: Path, retrieve: CachedRetrieval) -> dict:
    """Each frame's Top-1 retrieved pose as the estimate (the last one held through frames without an image)."""
    T = len(run)
    pose = np.zeros((T, 3))
    ms = np.zeros(T)
    last = None
    for t in range(T):
        if run.image_ids[t]:
            t0 = time.perf_counter()
            last = retrieve(Path(data) / run.image_ids[t])[0, :3]
            ms[t] = (time.perf_counter() - t0) * 1000.0
        pose[t] = last if last is not None else np.nan
    first = next(i for i in range(T) if run.image_ids[i])
    pose[:first] = pose[first]
    return {"pose": pose, "cov": np.zeros((T, 3, 3)), "state": ["image"] * T, "particles": np.zeros(T, np.int64),
            "updated": np.array([bool(i) for i in run.image_ids]), "best": np.ones(T), "ms": ms}


def replay_job(loc, data: Path, run, method: str, trial: int, threshold_m: float, hold: int) -> Replay:
    """One method's replay of one run, trial `trial`, with `loc`'s filter settings (restored afterwards).
    `loc.retrieved` should be a `CachedRetrieval` (image_only reads it)."""
    from pipeline.localize import replay_bundle, replay_one

    own = loc.filter_config
    try:
        if method in ("proposed", "image_reloc", "sequence"):
            mode = {"proposed": own.relocalise_with, "image_reloc": "image", "sequence": "sequence"}[method]
            loc.filter_config = own.model_copy(update={"relocalise_with": mode})
            rep = replay_bundle(run, loc, data, trial)
        elif method == "image_only":
            rep = image_only_replay(run, data, loc.retrieved)
        else:
            fcfg = own.model_copy(update={"seed": loc.base_seed, "method": method})
            rep = replay_one(run, loc.map, fcfg, loc.laser.base_from_laser, "uniform", trial)
    finally:
        loc.filter_config = own
    return measured(run, trial, rep, threshold_m, hold)
