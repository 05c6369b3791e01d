"""Stage `evaluate-places`: global descriptors of a place set measured variant by variant.

For each backbone and set of scales the images go through the trunk once (longest side at most
`max_side` pixels); each pooling (`sum`, the paper's IPA, or `gem`) and each whitening (`none`, `pca`
fitted on the database with every dimension it supports, `shrinkage`: regularised by the ratio of
dimensions to images) then make one variant. Queries are ranked against the database by cosine
similarity (exact: a place set is small).
With a detector, each one-scale variant is also re-ranked by RPA on its Top-N (`place_rerank`).
Outputs: metrics.json (R@1/5/10, mAP@4, milliseconds per image on this machine, per variant),
report.md (the table beside the sum-pooled, unwhitened ImageNet baseline), misses.png (the queries whose
Top-1 is wrong under the best variant, beside that Top-1 and a true match) and config.yaml.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.retrieval.descriptors import GEM_P, POOLINGS, ipa_descriptor  # noqa: F401 (POOLINGS: stages.places)
from pipeline.retrieval.metrics import map_at, recall_at, relevance
from pipeline.retrieval.place_set import load_places, load_tensor
from pipeline.retrieval.whitening import PCAWhitening, ShrinkageWhitening, l2_normalize

WHITENINGS = ("none", "pca", "shrinkage")
RECALL_AT = (1, 5, 10)


@dataclass(frozen=True)
class Variant:
    backbone: str
    pooling: str
    whitening: str
    scales: tuple[float, ...] = (1.0,)

    @property
    def label(self) -> str:
        ms = "" if self.scales == (1.0,) else " ms" + "/".join(f"{s:g}" for s in self.scales)
        return f"{self.backbone} {self.pooling}{ms} {self.whitening}"


def pool(fmap: np.ndarray, pooling: str, p: float = GEM_P) -> np.ndarray:
    """(C,) of a (C, h, w) map: sum over positions, or generalized mean (Radenovic et al.) of the map
    clamped at 1e-6 (a Lite trunk's linear bottleneck has negative activations), l2-normalised; the IPA's
    pooling (`pipeline.retrieval.descriptors.ipa_descriptor`, what `extract` does with `retrieval.pooling`)."""
    return ipa_descriptor(np.asarray(fmap, dtype=np.float64), pooling, p)  # float64: the sum as precise as GeM


def describe(backbone, paths: list[Path], scales: tuple[float, ...], poolings, max_side: int | None,
             progress: bool = False) -> tuple[dict[str, np.ndarray], float]:
    """{pooling: (N, C) descriptors} of the images (multi-scale: the scales' descriptors summed, then
    l2), and the milliseconds per image of the trunk and pooling on this machine."""
    import torch

    from pipeline.progress import progress_bar

    out = {p: [] for p in poolings}
    seconds = 0.0
    for path in progress_bar(paths, desc=f"describing with {backbone.name}", unit="image", enabled=progress,
                             leave=False):
        per = {p: [] for p in poolings}
        for s in scales:
            x = load_tensor(path, max_side, s)
            t0 = time.perf_counter()
            with torch.no_grad():
                fmap = backbone(x[None])[0][0].numpy()
            for p in poolings:
                per[p].append(pool(fmap, p))
            seconds += time.perf_counter() - t0
        for p in poolings:
            out[p].append(l2_normalize(np.sum(per[p], axis=0)))
    return {p: np.asarray(v, dtype=np.float32) for p, v in out.items()}, 1000.0 * seconds / max(len(paths), 1)


def whitened(kind: str, db: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Database and query descriptors under a whitening fitted on the database."""
    if kind == "none":
        return db, q, {"dims": int(db.shape[1])}
    w = PCAWhitening() if kind == "pca" else ShrinkageWhitening() if kind == "shrinkage" else None
    if w is None:
        raise ValueError(f"whitening must be one of {WHITENINGS}, got '{kind}'")
    w.fit(db)
    info = {"dims": int(w.n_components_), "cap": w.cap_reason_}
    if kind == "shrinkage":
        info["regularization"] = round(float(w.regularization_), 4)
    return w.transform(db), w.transform(q), info


def measure(db: np.ndarray, q: np.ndarray, positive: np.ndarray) -> tuple[dict, np.ndarray]:
    """Figures of one variant, and the ranking (Q, D) by cosine similarity."""
    return measure_ranking(np.argsort(-(q @ db.T), axis=1, kind="stable"), positive)


def measure_ranking(ranked: np.ndarray, positive: np.ndarray) -> tuple[dict, np.ndarray]:
    """R@1/5/10 and mAP@4 of a (Q, D) ranking."""
    rel = relevance(ranked, positive)
    has = positive.any(axis=1)
    figures = {f"recall@{n}": round(recall_at(rel, has, n), 4) for n in RECALL_AT}
    figures["map@4"] = round(map_at(rel, positive, 4), 4)
    return figures, ranked


def run_evaluate_places(cfg, *, inputs: dict[str, Path], outputs: dict[str, Path], backbones: list[str],
                        poolings: list[str], whitenings: list[str], scales: list[tuple[float, ...]],
                        max_side: int | None = 640, weights: dict[str, str] | None = None, run_stride: int = 10,
                        force: bool = False, progress: bool = True) -> Path:
    """Measure every variant on the place set `inputs['places']` (see module docstring); with
    `inputs['detector']` (a `train-detector` output) each one-scale variant is also re-ranked by RPA."""
    import torch

    from pipeline.config import write_effective_config
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.machine import machine_summary
    from pipeline.retrieval.backbones import load_backbone
    from pipeline.retrieval.place_figures import misses_figure

    ps = load_places(Path(inputs["places"]), run_stride=run_stride)
    out = Path(outputs["out"])
    read = [ps.root] + ([Path(inputs["detector"])] if inputs.get("detector") is not None else [])
    check_output(out, force=force, inputs=read)
    det = None
    if inputs.get("detector") is not None:
        from pipeline.detection.inference import load_detector

        det = load_detector(Path(inputs["detector"]), device="cpu")
    rows, rankings = [], {}
    loaded = {name: load_backbone(name, (weights or {}).get(name)) for name in backbones}
    if any(bb is None for bb in loaded.values()):
        raise ValueError("evaluate-places measures ImageNet trunks and checkpoints, not the detector")
    for name, bb in loaded.items():
        for sc in scales:
            db, ms_db = describe(bb, ps.database, sc, poolings, max_side, progress)
            q, ms_q = describe(bb, ps.queries, sc, poolings, max_side, progress)
            ms = (ms_db * len(ps.database) + ms_q * len(ps.queries)) / (len(ps.database) + len(ps.queries))
            for pooling in poolings:
                for wh in whitenings:
                    v = Variant(name, pooling, wh, tuple(sc))
                    d, qq, info = whitened(wh, db[pooling], q[pooling])
                    figures, ranked = measure(d, qq, ps.positive)
                    rows.append({"variant": v.label, **asdict(v), "rerank": None, **figures,
                                 "ms_per_image": round(ms, 1), **info, "weights": bb.source})
                    rankings[v.label] = ranked
    if det is not None and (1.0,) in [tuple(sc) for sc in scales]:
        rows += _reranked_rows(cfg, det, loaded, ps, rows, rankings, max_side, progress)
    best = max(rows, key=lambda r: (r["recall@1"], r["map@4"]))
    baseline = next((r for r in rows if r["pooling"] == "sum" and r["whitening"] == "none"
                     and tuple(r["scales"]) == (1.0,) and r["rerank"] is None), None)
    doc = {"place_set": ps.name, "root": str(ps.root), "database": len(ps.database), "queries": len(ps.queries),
           "queries_with_positives": ps.queries_with_positives, "max_side": max_side, "variants": rows,
           "best": best["variant"], "baseline": None if baseline is None else baseline["variant"],
           "machine": machine_summary(), "threads": torch.get_num_threads()}
    with atomic_dir(out, force=force, inputs=read) as tmp:
        misses = misses_figure(tmp / "misses.png", ps, rankings[best["variant"]], title=f"{ps.name}: {best['variant']}")
        doc["misses"] = misses
        write_text_atomic(tmp / "metrics.json", json.dumps(doc, indent=2) + "\n")
        write_text_atomic(tmp / "report.md", render_report(doc))
        write_effective_config(cfg, tmp, stage="evaluate-places", inputs={"places": ps.root})
    return out


def _reranked_rows(cfg, det, backbones: dict, ps, rows, rankings, max_side, progress) -> list[dict]:
    """The one-scale variants, re-ranked by RPA on their Top-N (`place_rerank`); one detector pass per image
    serves every backbone, and each +rpa row's time adds the detector's and its backbone's region pooling."""
    from pipeline.retrieval.place_rerank import describe_regions, reranked

    r = cfg.retrieval
    db, det_db, bb_db = describe_regions(det, backbones, ps.database, max_side, r, progress)
    q, det_q, bb_q = describe_regions(det, backbones, ps.queries, max_side, r, progress)
    images = len(ps.database) + len(ps.queries)
    out = []
    for row in [x for x in rows if tuple(x["scales"]) == (1.0,) and x["rerank"] is None]:
        name = row["backbone"]
        ms = 1000.0 * (det_db + det_q + bb_db[name] + bb_q[name]) / images
        ranked = reranked(rankings[row["variant"]], db[name], q[name], row["whitening"] != "none", r.top_n)
        figures, _ = measure_ranking(ranked, ps.positive)
        label = f"{row['variant']} +rpa"
        rankings[label] = ranked
        out.append({**row, **figures, "variant": label, "rerank": f"rpa top {r.top_n}",
                    "ms_per_image": round(row["ms_per_image"] + ms, 1)})
    return out


def render_report(doc: dict) -> str:
    base = next((r for r in doc["variants"] if r["variant"] == doc["baseline"]), None)
    lines = [f"# Place recognition on {doc['place_set']}", "",
             f"{doc['database']} database images, {doc['queries']} queries ({doc['queries_with_positives']} with a "
             f"true match); longest side at most {doc['max_side'] or 'as recorded'} px; "
             f"{doc['threads']} torch thread(s) on {doc['machine']}.", "",
             "| variant | R@1 | R@5 | R@10 | mAP@4 | R@1 vs baseline | dims | ms / image |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(doc["variants"], key=lambda r: (-r["recall@1"], -r["map@4"])):
        diff = "" if base is None else f"{r['recall@1'] - base['recall@1']:+.2f}"
        lines.append(f"| {r['variant']} | {r['recall@1']:.3f} | {r['recall@5']:.3f} | {r['recall@10']:.3f} | "
                     f"{r['map@4']:.3f} | {diff} | {r['dims']} | {r['ms_per_image']:.1f} |")
    lines += ["", f"Baseline: {doc['baseline']} (ImageNet features, sum pooling, no whitening). Best: {doc['best']}; "
              f"its {doc['misses']['wrong']} wrong Top-1 of {doc['misses']['queries']} queries are in misses.png "
              f"(the first {doc['misses']['shown']} shown).", ""]
    return "\n".join(lines)
