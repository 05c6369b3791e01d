"""Stage `prior evaluate`: seed 001's experiments on a site (its Table I and layer-weight comparison).

Database: the `train` split of the capture images; queries: the `test` split (whole held-out stops), and
with `changed` every image of the site after `synth --change` against the same database. Measures:

- Table I: per compression (IPCA, KPCA, SRP, GRP, uncompressed) the memory a query needs (the
  compression's arrays plus the database vectors, mean over the three layers, as the paper), the time of
  one query (three layers: compression, ball tree k=10, scoring), the share of queries with their
  (room, area) among the k neighbours (the paper's "returns the correct index", mean over the layers),
  and top-1 area and room accuracy with the configured measure and layer weights.
- Per measure (spearman, pearson, euclidean, gaussian) x layer weights: top-1 area and room accuracy.
- With a bundle and the ingested site: global localization seeded three ways on the same query runs
  (the steps before their first kidnapping): particles over the first image's most probable areas (the
  prior), around its Top-4 retrieved poses (seed 000), or uniform; steps to converge.

Outputs: metrics.json, report.md, the PNGs, config.yaml, and for DVC (`pipeline.io.tracked`, see
`write_tracked`) headline.json (Table I's best and configured accuracies; with the seeding comparison
each seeding's convergence and the prior's hit rates) and, with the seeding comparison,
plots/seeding.csv (`steps,area_prior,candidates,uniform`: the share of replays converged by then).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.prior.features import select
from pipeline.prior.model import MEASURES, AreaPrior, PriorSettings

WEIGHT_GRID = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1 / 3, 1 / 3, 1 / 3), (0.6, 0.3, 0.1),
               (0.1, 0.3, 0.6), (0.5, 0.5, 0.0), (0.5, 0.0, 0.5), (0.0, 0.5, 0.5))
COMPRESSIONS = ("ipca", "kpca", "srp", "grp", "none")


def settings_of(cfg: SitelocConfig) -> PriorSettings:
    p = cfg.prior
    return PriorSettings(p.k, p.leaf_size, p.measure, tuple(p.layer_weights), p.temperature, p.index)


def build_prior(cfg: SitelocConfig, meta: dict, raw: dict, encoder: dict, compression: str | None = None) -> AreaPrior:
    p = cfg.prior
    return AreaPrior.build(meta, raw, compression=compression or p.compression, n_components=p.n_components,
                           seed=p.seed, settings=settings_of(cfg), encoder=encoder, shrinkage=p.shrinkage)


def truth(prior: AreaPrior, meta: dict) -> np.ndarray:
    """Class index of each query (-1 when its (room, area) is not in the database)."""
    index = {c: i for i, c in enumerate(prior.classes)}
    return np.array([index.get((r, a), -1) for r, a in zip(meta["room"], meta["area"], strict=True)])


def accuracy(prior: AreaPrior, probs: np.ndarray, labels: np.ndarray, rooms: list[str]) -> dict:
    pred = probs.argmax(axis=1)
    room_of = np.array([c[0] for c in prior.classes])
    return {"area": round(float(np.mean(pred == labels)), 4),
            "room": round(float(np.mean(room_of[pred] == np.asarray(rooms))), 4)}


def weight_grid(prior: AreaPrior, raw_q: dict, meta_q: dict) -> dict:
    """{measure: [{weights, area, room}]} over WEIGHT_GRID."""
    labels = truth(prior, meta_q)
    compressed = prior.compress(raw_q)
    found = prior.neighbours(compressed)
    out = {}
    for measure in MEASURES:
        per = prior.layer_probabilities(compressed, measure, found)
        out[measure] = [{"weights": [round(w, 3) for w in ws],
                         **accuracy(prior, prior.combine(per, ws), labels, meta_q["room"])} for ws in WEIGHT_GRID]
    return out


def table_one(cfg: SitelocConfig, meta_db, raw_db, meta_q, raw_q, encoder, *, changed=None, timed: int = 100,
              progress: bool = True) -> list[dict]:
    """One row per compression; `changed`: (meta, raw) of the changed site's queries, for their accuracy."""
    from pipeline.progress import progress_bar

    rows = []
    for comp in progress_bar(COMPRESSIONS, desc="table I", unit="compression", enabled=progress):
        t0 = time.perf_counter()
        prior = build_prior(cfg, meta_db, raw_db, encoder, comp)
        build_s = time.perf_counter() - t0
        labels = truth(prior, meta_q)
        compressed = prior.compress(raw_q)
        found = prior.neighbours(compressed)
        hit = np.mean([np.mean([labels[q] in prior.labels[found[n][1][q]] for q in range(len(labels))])
                       for n in prior.layers])
        acc = accuracy(prior, prior.combine(prior.layer_probabilities(compressed, found=found)), labels,
                       meta_q["room"])
        n_t = min(timed, len(labels))
        prior.probabilities({n: raw_q[n][:1] for n in prior.layers})  # trees and caches built before timing
        t0 = time.perf_counter()
        for q in range(n_t):
            prior.probabilities({n: raw_q[n][q:q + 1] for n in prior.layers})
        query_s = (time.perf_counter() - t0) / max(n_t, 1)
        if changed is not None:
            c_acc = accuracy(prior, prior.probabilities(changed[1]), truth(prior, changed[0]), changed[0]["room"])
        mem = prior.nbytes()
        rows.append({"compression": comp,
                     "dims": {n: int(prior.vectors[n].shape[1]) for n in prior.layers},
                     "memory_kb_mean_layer": round(float(np.mean(list(mem.values()))) / 1024, 1),
                     "memory_kb_by_layer": {n: round(v / 1024, 1) for n, v in mem.items()},
                     "query_ms": round(query_s * 1000, 3), "build_s": round(build_s, 2),
                     f"hit_at_{prior.settings.k}": round(float(hit), 4), "area_accuracy": acc["area"],
                     "room_accuracy": acc["room"],
                     **({"changed_area_accuracy": c_acc["area"], "changed_room_accuracy": c_acc["room"]}
                        if changed is not None else {})})
    return rows


def append_study(cfg: SitelocConfig, meta_db, raw_db, meta_q, raw_q, encoder, *, every: int = 5) -> dict:
    """The paper's scalability claim, measured: a prior built without every `every`-th room, then those
    rooms' database images appended. Compared with building on everything at once: the time, the held-out
    rooms' queries before and after, and how many of the other queries keep their answer."""
    rooms = sorted(set(meta_db["room"]))
    late = set(rooms[::every])
    first = np.array([r not in late for r in meta_db["room"]])
    t0 = time.perf_counter()
    prior = build_prior(cfg, *select(meta_db, raw_db, first), encoder)
    build_s = time.perf_counter() - t0
    q_late = np.array([r in late for r in meta_q["room"]])
    before = prior.probabilities(raw_q)
    pred_before = [prior.classes[k] for k in before.argmax(axis=1)]
    t0 = time.perf_counter()
    prior.append(*select(meta_db, raw_db, ~first))
    append_s = time.perf_counter() - t0
    after = prior.probabilities(raw_q)
    pred_after = [prior.classes[k] for k in after.argmax(axis=1)]
    truth_q = list(zip(meta_q["room"], meta_q["area"], strict=True))
    t0 = time.perf_counter()
    full = build_prior(cfg, meta_db, raw_db, encoder)
    full_s = time.perf_counter() - t0
    pred_full = [full.classes[k] for k in full.probabilities(raw_q).argmax(axis=1)]

    def acc(pred, sel):
        idx = np.flatnonzero(sel)
        return round(float(np.mean([pred[i] == truth_q[i] for i in idx])), 4) if len(idx) else None

    old = ~q_late
    return {"rooms_appended": len(late), "images_appended": int((~first).sum()), "images_first": int(first.sum()),
            "build_first_s": round(build_s, 3), "append_s": round(append_s, 3), "build_all_s": round(full_s, 3),
            "late_queries": int(q_late.sum()), "late_area_accuracy_before": acc(pred_before, q_late),
            "late_area_accuracy_after": acc(pred_after, q_late), "late_area_accuracy_built_at_once":
                acc(pred_full, q_late),
            "other_queries": int(old.sum()), "other_area_accuracy_before": acc(pred_before, old),
            "other_area_accuracy_after": acc(pred_after, old),
            "other_unchanged_share": round(float(np.mean([a == b for a, b, o in zip(pred_before, pred_after, old,
                                                                                      strict=True) if o])), 4)}


def headline(metrics: dict) -> dict:
    """The figures compared across runs: Table I's best top-1 accuracies (over the compressions) and the
    configured compression's, on the changed site too when measured; with the seeding comparison, each
    seeding's converged / within-15 counts and median steps, and how often the prior's areas held the truth."""
    rows = metrics["table_one"]
    conf = next((r for r in rows if r["compression"] == metrics["settings"]["compression"]), {})
    t1 = {"area_accuracy_best": max(r["area_accuracy"] for r in rows),
          "room_accuracy_best": max(r["room_accuracy"] for r in rows),
          "area_accuracy": conf.get("area_accuracy"), "room_accuracy": conf.get("room_accuracy")}
    if rows and all("changed_area_accuracy" in r for r in rows):
        t1["changed_area_accuracy_best"] = max(r["changed_area_accuracy"] for r in rows)
        t1["changed_room_accuracy_best"] = max(r["changed_room_accuracy"] for r in rows)
    out = {"table_one": t1}
    if "seeding" in metrics:
        sd = metrics["seeding"]
        out["seeding"] = {k: sd[k] for k in ("prior_hit_rate", "prior_top1_rate", "retrieval_top1_rate")}
        for name, v in sd["summary"].items():
            out[f"seeding_{name}"] = {k: v[k] for k in ("replays", "converged", "within_15", "converged_step_median")}
    return out


def seeding_table(seeding: dict) -> tuple[list[str], list[tuple]]:
    """(columns, rows) of plots/seeding.csv: per step s of a segment (0 to the longest segment's last), the
    share of each seeding's replays converged at step <= s (seeding.png's curves; never-converged replays
    count in the denominator)."""
    reps = seeding["replays"]
    longest = max((r["steps"] for rs in reps.values() for r in rs), default=0)
    conv = {m: np.sort([r["converged_step"] for r in rs if r["converged_step"] is not None]) for m, rs in reps.items()}
    steps = np.arange(longest)
    share = {m: np.searchsorted(conv[m], steps, side="right") / len(rs) if rs else [None] * len(steps)
             for m, rs in reps.items()}
    return ["steps", *reps], [(int(t), *(share[m][i] for m in reps)) for i, t in enumerate(steps)]


def write_tracked(out: Path, metrics: dict) -> None:
    from pipeline.io.tracked import write_headline, write_plot_table

    write_headline(out, headline(metrics))
    if "seeding" in metrics:
        write_plot_table(out, "seeding", *seeding_table(metrics["seeding"]))


def run_prior_evaluate(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True) -> Path:
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.prior.features import read_layers
    from pipeline.prior.report import write_examples, write_figures, write_report

    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    meta, raw, rep = read_layers(Path(inputs["features"]))
    split = np.asarray(meta["split"])
    db, q = np.flatnonzero(split == "train"), np.flatnonzero(split != "train")
    if len(db) < 2 or len(q) == 0:
        from pipeline.errors import InputError, Problem

        raise InputError(f"{inputs['features']}: nothing to evaluate", [Problem(
            str(inputs["features"]), f"{len(db)} train and {len(q)} test images",
            fix="ingest with a test split (ingest.split.test_fraction > 0)")])
    meta_db, raw_db = select(meta, raw, db)
    meta_q, raw_q = select(meta, raw, q)
    metrics = {"site": {"database_images": len(db), "query_images": len(q),
                        "classes": len(set(zip(meta_db["room"], meta_db["area"], strict=True))),
                        "rooms": len(set(meta_db["room"]))},
               "encoder": rep["encoder"], "settings": cfg.prior.model_dump(mode="json")}
    changed = None
    if inputs.get("changed"):
        meta_c, raw_c, rep_c = read_layers(Path(inputs["changed"]))
        if rep_c["encoder"]["backbone"] != rep["encoder"]["backbone"] or rep_c["dims"] != rep["dims"]:
            from pipeline.errors import InputError, Problem

            raise InputError(f"{inputs['changed']}: other features", [Problem(
                str(inputs["changed"]), f"encoded with {rep_c['encoder']['backbone']} {rep_c['dims']}, the "
                f"database with {rep['encoder']['backbone']} {rep['dims']}",
                fix="run `siteloc prior features` on the changed site with the same config")])
        changed = (meta_c, raw_c)
    metrics["table_one"] = table_one(cfg, meta_db, raw_db, meta_q, raw_q, rep["encoder"], changed=changed,
                                     progress=progress)
    prior = build_prior(cfg, meta_db, raw_db, rep["encoder"])
    metrics["layers"] = list(prior.layers)
    metrics["weights"] = weight_grid(prior, raw_q, meta_q)
    if changed is not None:
        metrics["changed"] = {"query_images": len(meta_c["image_id"]), "weights": weight_grid(prior, raw_c, meta_c)}
    metrics["append"] = append_study(cfg, meta_db, raw_db, meta_q, raw_q, rep["encoder"])
    if inputs.get("bundle") and inputs.get("data"):
        from pipeline.prior.seeding import compare_seeding

        metrics["seeding"] = compare_seeding(cfg, prior, Path(inputs["bundle"]), Path(inputs["data"]),
                                             progress=progress)
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_tracked(tmp, metrics)
        figures = write_figures(tmp, metrics)
        if rep.get("data") and write_examples(tmp / "examples.png", prior, meta_q, prior.probabilities(raw_q),
                                              Path(rep["data"])):
            figures.append("examples.png")
        write_report(tmp / "report.md", metrics, figures)
        write_effective_config(cfg, tmp, stage="prior-evaluate", inputs=inputs)
    return out
