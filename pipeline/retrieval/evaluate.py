"""Stage `evaluate-retrieval`: IPA-only vs IPA + RPA re-ranking, for each whitening, on held-out queries.

Database: the extraction's images of the ingest's `train` split (mapping stops). Queries: the `test`
stops and the frames of every run whose name does not start with "mapping". For each whitening (none,
PCA, learned from geo-tag pairs) the transforms are fitted on the database only, then every query is
answered with the IPA Top-N and with its RPA re-ranking. Measures (see `metrics`): mAP@4 (the paper's
figure) and recall@{1, 4, 10, 50}, with positives within {1, 2, 5} m and {30, 60} degrees.
Outputs: metrics.json (every variant and threshold; `by_source`: the configured variant's figures for test
stops and run frames apart), report.md (the tables), recall.png (recall@N curves
at 2 m / 30 deg), examples.png (queries and their Top-4, green when a positive), config.yaml, and for
DVC (`pipeline.io.tracked`, see `write_tracked`) headline.json (mAP@4 and recall@1 of IPA and IPA + RPA
with the configured whitening at 2 m / 30 deg) and plots/recall_at_n.csv (`n,ipa,ipa_rpa`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io import tables
from pipeline.retrieval.search import query_region_order, region_offsets

DISTANCES = (1.0, 2.0, 5.0)
HEADINGS = (30.0, 60.0)
RECALL_AT = (1, 4, 10, 50)
MAIN = (2.0, 30.0)
FAR_M = 10.0  # a Top-1 farther than this is a gross error: another part of the floor


@dataclass
class Extracted:
    image_ids: list[str]
    poses: np.ndarray  # (N, 3)
    groups: np.ndarray
    splits: np.ndarray
    ipa: np.ndarray  # (N, D) l2-normalised, not whitened
    rpa: np.ndarray | None  # (M, Dr), rows grouped by image in catalog order; None: left in rpa_path
    offsets: np.ndarray  # (N + 1,)
    rpa_source: np.ndarray | None  # (M,)
    rpa_score: np.ndarray | None  # (M,)
    rpa_path: Path | None = None

    def regions_at(self, rows: np.ndarray) -> np.ndarray:
        """The region descriptors of the sorted region rows `rows`, from memory or read from the file."""
        if self.rpa is not None:
            return self.rpa[rows]
        from pipeline.retrieval.region_stream import read_rows

        return read_rows(self.rpa_path, rows)


def load_extracted(path: Path, *, regions: bool = True) -> Extracted:
    """An extraction; `regions` False leaves the region table on disk (offsets only: `build-index` of a site
    whose regions outgrow memory reads them a batch at a time, `pipeline.retrieval.region_stream`)."""
    path = Path(path)
    cat = tables.read_table(path / "catalog.parquet", "catalog").to_pydict()
    ipa_t = tables.read_table(path / "ipa.parquet", "ipa")
    ids = cat["image_id"]
    if ipa_t.column("image_id").to_pylist() != ids:
        raise InputError(f"{path}: ipa.parquet and catalog.parquet list different images",
                         [Problem(str(path / "ipa.parquet"), "image order differs", fix="re-run `siteloc extract`")])
    poses = np.column_stack([cat["x"], cat["y"], cat["theta"]])
    if not regions:
        from pipeline.retrieval.region_stream import region_offsets_streamed

        offsets = region_offsets_streamed(path / "rpa.parquet", ids)
        return Extracted(ids, poses, np.asarray(cat["group"]), np.asarray(cat["split"]),
                         tables.descriptor_matrix(ipa_t), None, offsets, None, None, path / "rpa.parquet")
    rpa_t = tables.read_table(path / "rpa.parquet", "rpa")
    try:
        offsets = region_offsets(ids, rpa_t.column("image_id").to_pylist())
    except (ValueError, KeyError):
        raise InputError(f"{path}: rpa.parquet rows are not grouped by the catalog's images",
                         [Problem(str(path / "rpa.parquet"), "rows out of order or of unknown images",
                                  fix="re-run `siteloc extract`")]) from None
    return Extracted(ids, poses, np.asarray(cat["group"]), np.asarray(cat["split"]), tables.descriptor_matrix(ipa_t),
                     tables.descriptor_matrix(rpa_t), offsets, np.asarray(rpa_t.column("source").to_pylist()),
                     rpa_t.column("score").to_numpy(), path / "rpa.parquet")


def split_database_queries(ex: Extracted) -> tuple[np.ndarray, np.ndarray]:
    db = np.flatnonzero(ex.splits == "train")
    query = np.flatnonzero((ex.splits == "test") | np.char.startswith(ex.splits.astype(str), "run:")
                           & ~np.char.startswith(ex.splits.astype(str), "run:mapping"))
    return db, query


def query_regions(ex: Extracted, i: int, n: int) -> np.ndarray:
    """Row indices (into ex.rpa) of image i's regions used as query regions: detections first, by score."""
    rows = np.arange(ex.offsets[i], ex.offsets[i + 1])
    return rows[query_region_order(ex.rpa_source[rows], ex.rpa_score[rows], n)]


def fit_whitenings(ex: Extracted, db: np.ndarray, kind: str, cfg) -> tuple:
    """(IPA transform, RPA transform) fitted on the database; identity functions for 'none'."""
    from pipeline.retrieval.whitening import LearnedWhitening, PCAWhitening, ShrinkageWhitening, geo_pairs

    if kind == "none":
        return None, None
    db_rows = region_rows(ex, db)
    rng = np.random.default_rng(0)
    sample = rng.choice(db_rows, size=min(len(db_rows), 100_000), replace=False) if len(db_rows) else db_rows
    rpa_w = PCAWhitening(cfg.rpa_dims).fit(ex.regions_at(np.sort(sample)))
    if kind == "pca":
        return PCAWhitening(cfg.ipa_dims).fit(ex.ipa[db]), rpa_w
    if kind == "shrinkage":
        return ShrinkageWhitening().fit(ex.ipa[db]), rpa_w
    pairs = geo_pairs(ex.poses[db, :2], ex.poses[db, 2], ex.groups[db], max_distance=cfg.pair_distance,
                      max_heading_deg=cfg.pair_heading_deg)
    if len(pairs) < 2 * ex.ipa.shape[1]:
        raise InputError(f"learned whitening: {len(pairs)} image pairs within {cfg.pair_distance} m and "
                         f"{cfg.pair_heading_deg} deg, fewer than twice the {ex.ipa.shape[1]} dimensions",
                         [Problem("retrieval.pair_distance", "too few positive pairs between database stops",
                                  fix="raise retrieval.pair_distance / pair_heading_deg, or use whitening pca")])
    return LearnedWhitening(cfg.ipa_dims).fit(ex.ipa[db], pairs), rpa_w


def _apply(w, x):
    return x if w is None else w.transform(x)


def region_rows(ex: Extracted, images: np.ndarray) -> np.ndarray:
    """Row indices into ex.rpa of the regions of `images`, image by image."""
    return np.concatenate([np.arange(ex.offsets[i], ex.offsets[i + 1]) for i in images] + [np.zeros(0, np.int64)])


def whitened_database(ex: Extracted, db: np.ndarray, w_ipa, w_rpa):
    """The search Database of images `db` of an extraction, whitened by the given transforms (None: as is)."""
    from pipeline.retrieval.search import Database

    offsets = np.concatenate([[0], np.cumsum(np.diff(ex.offsets)[db])])
    return Database([ex.image_ids[i] for i in db], ex.poses[db], _apply(w_ipa, ex.ipa[db]),
                    _apply(w_rpa, ex.rpa[region_rows(ex, db)]), offsets)


def rank_all(ex: Extracted, db: np.ndarray, qx: Extracted, queries: np.ndarray, whitening: str, cfg) -> dict:
    """Ranked database positions (into `db` of `ex`) of every query (`queries` of `qx`): IPA only and after
    RPA re-ranking."""
    from pipeline.retrieval.search import make_index, rerank

    w_ipa, w_rpa = fit_whitenings(ex, db, whitening, cfg)
    database = whitened_database(ex, db, w_ipa, w_rpa)
    index = make_index(cfg.index, database.ipa, cfg.index_params)
    _, first = index.search(_apply(w_ipa, qx.ipa[queries]), cfg.top_n)
    reranked = np.empty_like(first)
    for k, q in enumerate(queries):
        regions = _apply(w_rpa, qx.rpa[query_regions(qx, q, cfg.query_regions)])
        reranked[k] = rerank(database, first[k], regions)[0]
    dims = {"ipa": int(database.ipa.shape[1]), "rpa": int(database.rpa.shape[1])}
    if w_ipa is not None:
        dims["ipa_cap"] = str(w_ipa.cap_reason_)
    return {"ipa": first, "ipa+rpa": reranked, "dims": dims}


def measure(ranked: np.ndarray, query_poses: np.ndarray, db_poses: np.ndarray) -> dict:
    from pipeline.retrieval.metrics import map_at, positives, recall_at, relevance, top1_distances

    out = {}
    for d in DISTANCES:
        for h in HEADINGS:
            pos = positives(query_poses, db_poses, d, h)
            rel = relevance(ranked, pos)
            has = pos.any(axis=1)
            out[f"{d:g}m_{h:g}deg"] = {"map_at_4": map_at(rel, pos, 4),
                                       **{f"recall_at_{n}": recall_at(rel, has, n) for n in RECALL_AT},
                                       "queries_with_positive": int(has.sum())}
    far = top1_distances(ranked, query_poses, db_poses)
    out["top1"] = {"median_m": float(np.median(far)), f"beyond_{FAR_M:g}m": float(np.mean(far > FAR_M))}
    return out


def query_sources(splits: np.ndarray) -> np.ndarray:
    """(Q,) "test stops" or "run frames" for each query's split ("test" or "run:<name>")."""
    return np.where(np.asarray(splits).astype(str) == "test", "test stops", "run frames")


def by_source(ranked: np.ndarray, sources: np.ndarray, query_poses: np.ndarray, db_poses: np.ndarray) -> dict:
    """The main threshold's figures per query source, with what makes one source harder than another: how
    far its queries stand from the nearest database image and how many positives each has."""
    from scipy.spatial import cKDTree

    from pipeline.retrieval.metrics import map_at, positives, recall_at, relevance

    out, tree = {}, cKDTree(db_poses[:, :2])
    for source in sorted(set(sources.tolist())):
        m = sources == source
        pos = positives(query_poses[m], db_poses, *MAIN)
        rel, has = relevance(ranked[m], pos), pos.any(axis=1)
        nearest = tree.query(query_poses[m, :2])[0]
        out[source] = {"queries": int(m.sum()), "queries_with_positive": int(has.sum()),
                       "nearest_database_m_median": float(np.median(nearest)),
                       "positives_mean": float(pos.sum(axis=1)[has].mean()) if has.any() else float("nan"),
                       "map_at_4": map_at(rel, pos, 4), "recall_at_1": recall_at(rel, has, 1),
                       "recall_at_4": recall_at(rel, has, 4)}
    return out


def run_evaluate_retrieval(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                           force: bool = False, progress: bool = True) -> Path:
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.retrieval.figures import examples_figure, recall_figure

    r = cfg.retrieval
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    ex = load_extracted(Path(inputs["descriptors"]))
    db, queries = split_database_queries(ex)
    qx, query_root = ex, Path(inputs["data"])
    if inputs.get("query_descriptors"):  # queries from another extraction, e.g. the site after `synth --change`
        qx, query_root = load_extracted(Path(inputs["query_descriptors"])), Path(inputs["query_data"])
        _, queries = split_database_queries(qx)
        if qx.ipa.shape[1] != ex.ipa.shape[1]:
            raise InputError("the two extractions have different descriptor sizes",
                             [Problem(str(inputs["query_descriptors"]), f"{qx.ipa.shape[1]}-d, database "
                                      f"{ex.ipa.shape[1]}-d", fix="extract both with the same detector")])
        from pipeline.retrieval.backbones import recorded_backbone

        a, b = (recorded_backbone(Path(inputs[k])) or {} for k in ("descriptors", "query_descriptors"))
        if (a.get("name", "detector"), a.get("weights_sha256")) != (b.get("name", "detector"), b.get("weights_sha256")):
            raise InputError("the two extractions pool the maps of different retrieval backbones",
                             [Problem(str(inputs["query_descriptors"]), f"{b.get('name', 'detector')}, database "
                                      f"{a.get('name', 'detector')}", fix="extract both with the same "
                                      "retrieval.backbone and retrieval.backbone_weights")])
        from pipeline.retrieval.descriptors import pooling_label, pooling_sets, recorded_pooling

        a, b = (recorded_pooling(json.loads(p.read_text()) if p.is_file() else None)
                for p in (Path(inputs[k]) / "report.json" for k in ("descriptors", "query_descriptors")))
        if a != b:
            raise InputError("the two extractions pool their IPA differently",
                             [Problem(str(inputs["query_descriptors"]), f"retrieval.pooling {pooling_label(*b)}, "
                                      f"database {pooling_label(*a)}", fix=f"extract both with {pooling_sets(*a)}")])
    if len(db) < 2 or len(queries) == 0:
        raise InputError(f"{inputs['descriptors']}: {len(db)} database and {len(queries)} query images",
                         [Problem(str(Path(inputs["descriptors"]) / "catalog.parquet"),
                                  "retrieval needs train stops (database) and test stops or query runs",
                                  fix="ingest with a test share, or synthesise query runs")])
    results, rankings, skipped = {}, {}, {}
    for whitening in ("none", "pca", "shrinkage", "learned"):
        try:
            ranked = rank_all(ex, db, qx, queries, whitening, r)
        except InputError as exc:
            skipped[whitening] = str(exc)
            continue
        for stage in ("ipa", "ipa+rpa"):
            name = f"{stage} / {whitening}"
            rankings[name] = ranked[stage]
            results[name] = {"dims": ranked["dims"], **measure(ranked[stage], qx.poses[queries], ex.poses[db])}
    metrics = {"database_images": int(len(db)), "query_images": int(len(queries)), "top_n": r.top_n,
               "queries_from": str(inputs.get("query_descriptors") or inputs["descriptors"]),
               "query_regions": r.query_regions, "variants": results, "skipped": skipped,
               "paper_map_at_4": 0.742}
    whitening = r.whitening if r.whitening not in skipped else "pca"
    best = f"ipa+rpa / {whitening}"
    metrics["by_source"] = {"variant": best, "sources": by_source(rankings[best], query_sources(qx.splits[queries]),
                                                                  qx.poses[queries], ex.poses[db])}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_tracked(tmp, metrics, whitening)
        write_text_atomic(tmp / "report.md", report_table(metrics))
        recall_figure(tmp / "recall.png", rankings, qx.poses[queries], ex.poses[db], MAIN)
        examples_figure(tmp / "examples.png", (Path(inputs["data"]), ex, db), (query_root, qx, queries),
                        rankings[best], MAIN, title=best)
        write_effective_config(cfg, tmp, stage="evaluate-retrieval", inputs=inputs)
    return out


def write_tracked(out: Path, metrics: dict, whitening: str) -> None:
    """headline.json and plots/recall_at_n.csv of `whitening`'s IPA and IPA + RPA variants at 2 m / 30 deg:
    {"ipa": {"map_at_4", "recall_at_1"}, "ipa_rpa": {...}}, and one row per N of metrics.json's recall@N."""
    from pipeline.io.tracked import write_headline, write_plot_table

    key = f"{MAIN[0]:g}m_{MAIN[1]:g}deg"
    main = {stage.replace("+", "_"): metrics["variants"][f"{stage} / {whitening}"][key] for stage in ("ipa", "ipa+rpa")}
    write_headline(out, {s: {"map_at_4": m["map_at_4"], "recall_at_1": m["recall_at_1"]} for s, m in main.items()})
    ns = sorted(int(k.removeprefix("recall_at_")) for k in main["ipa"] if k.startswith("recall_at_"))
    write_plot_table(out, "recall_at_n", ["n", "ipa", "ipa_rpa"],
                     [(n, main["ipa"][f"recall_at_{n}"], main["ipa_rpa"][f"recall_at_{n}"]) for n in ns])


def report_table(metrics: dict) -> str:
    key = f"{MAIN[0]:g}m_{MAIN[1]:g}deg"
    lines = [f"# Retrieval: {metrics['database_images']} database images, {metrics['query_images']} queries",
             "", f"Positives within {MAIN[0]:g} m and {MAIN[1]:g} deg. The paper reports mAP@4 = 0.742.", "",
             f"| variant | dims (IPA / RPA) | mAP@4 | R@1 | R@4 | R@10 | R@50 | Top-1 beyond {FAR_M:g} m |",
             "|---|---|---|---|---|---|---|---|"]
    for name, v in metrics["variants"].items():
        m = v[key]
        far = v.get("top1", {}).get(f"beyond_{FAR_M:g}m", float("nan"))
        lines.append(f"| {name} | {v['dims']['ipa']} / {v['dims']['rpa']} | {m['map_at_4']:.3f} | "
                     + " | ".join(f"{m[f'recall_at_{n}']:.3f}" for n in RECALL_AT) + f" | {far:.3f} |")
    for name, why in metrics.get("skipped", {}).items():
        lines.append(f"\n{name} whitening skipped: {why}")
    lines += ["", "mAP@4 at every threshold:", "", "| variant | " + " | ".join(
        f"{d:g} m {h:g} deg" for d in DISTANCES for h in HEADINGS) + " |",
        "|---|" + "---|" * (len(DISTANCES) * len(HEADINGS))]
    for name, v in metrics["variants"].items():
        lines.append(f"| {name} | " + " | ".join(f"{v[f'{d:g}m_{h:g}deg']['map_at_4']:.3f}"
                                              for d in DISTANCES for h in HEADINGS) + " |")
    if "by_source" in metrics:
        lines += ["", f"{metrics['by_source']['variant']} by query source:", "",
                  "| queries | count | with a positive | nearest database image (median) | positives (mean) | mAP@4 "
                  "| R@1 | R@4 |", "|---|---|---|---|---|---|---|---|"]
        for source, t in metrics["by_source"]["sources"].items():
            lines.append(f"| {source} | {t['queries']} | {t['queries_with_positive']} | "
                         f"{t['nearest_database_m_median']:.2f} m | {t['positives_mean']:.2f} | {t['map_at_4']:.3f} | "
                         f"{t['recall_at_1']:.3f} | {t['recall_at_4']:.3f} |")
    return "\n".join(lines) + "\n"
