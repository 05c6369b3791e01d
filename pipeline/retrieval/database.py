"""Stage `build-index`: the retrieval database the runtime queries, and the query function it reuses.

`run_build_index` fits the configured whitening (`retrieval.whitening`: pca, shrinkage, learned or none) on the
database images of an extraction (the ingest's `train` stops), applies it, and writes into its output:
`database_ipa.parquet` and `database_rpa.parquet` (whitened, l2-normalised), `catalog.parquet` (poses),
`ipa_whitening.npz` / `rpa_whitening.npz` (arrays only) and `config.yaml`. An extraction with a retrieval
backbone other than the detector's map has its record copied into report.json (`retrieval_backbone`), so
`query` and `export` describe new images with the same backbone (`backbones.check_backbone`); the
extraction's IPA pooling is copied likewise (`ipa_pooling`, `gem_p`: `descriptors.check_pooling`).

`load_database(dir)` reads it back (numpy and pyarrow only) and `query_database` answers one query from
its raw (unwhitened) IPA and region descriptors with the two-stage retrieval of `search`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.io import tables


@dataclass
class RetrievalDatabase:
    db: object  # search.Database
    index: object
    ipa_whitening: object | None
    rpa_whitening: object | None
    settings: dict


def run_build_index(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                    force: bool = False) -> Path:
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.retrieval.evaluate import fit_whitenings, load_extracted, split_database_queries
    from pipeline.retrieval.region_stream import whitened_parts

    r = cfg.retrieval
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    from pipeline.retrieval.backbones import recorded_backbone

    # The regions stay on disk: sampled to fit their whitening, then whitened a batch at a time into the
    # memory-mapped region file (a site of 10^6 images has ~45 GB of them).
    ex = load_extracted(Path(inputs["descriptors"]), regions=False)
    backbone = recorded_backbone(Path(inputs["descriptors"]))
    from pipeline.retrieval.descriptors import pooling_record, recorded_pooling

    report = Path(inputs["descriptors"]) / "report.json"
    pooling = pooling_record(*recorded_pooling(json.loads(report.read_text()) if report.is_file() else None))
    db, _ = split_database_queries(ex)
    w_ipa, w_rpa = fit_whitenings(ex, db, r.whitening, r)
    ids = [ex.image_ids[i] for i in db]
    ipa = ex.ipa[db] if w_ipa is None else w_ipa.transform(ex.ipa[db])
    keep = np.zeros(len(ex.image_ids), dtype=bool)
    keep[db] = True
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        tables.write_table(tmp / "database_ipa.parquet", tables.to_table(
            "ipa", {"image_id": ids, "descriptor": tables.descriptor_array(ipa)}), "ipa")
        regions = whitened_parts(ex.rpa_path, ex.offsets, keep, (lambda x: x) if w_rpa is None else w_rpa.transform)
        n_regions = tables.write_table_parts(tmp / RPA_FILE, regions, "rpa")
        rpa_dim = tables.read_table(tmp / RPA_FILE, "rpa").schema.field("descriptor").type.list_size
        tables.write_table(tmp / "catalog.parquet", tables.to_table("catalog", {
            "image_id": ids, "x": ex.poses[db, 0], "y": ex.poses[db, 1], "theta": ex.poses[db, 2],
            "group": ex.groups[db], "split": ex.splits[db]}), "catalog")
        for name, w in (("ipa", w_ipa), ("rpa", w_rpa)):
            if w is not None:
                w.save(tmp / f"{name}_whitening.npz")
        if r.index in SAVED_KINDS:  # a graph or inverted file of 10^6 images takes minutes: built once, here
            from pipeline.retrieval.index import INDEX_FILE, make_index

            make_index(r.index, ipa, r.index_params).save(tmp / INDEX_FILE)
        write_text_atomic(tmp / "report.json", json.dumps({
            "images": len(ids), "regions": int(n_regions), "whitening": r.whitening,
            "index": r.index, "index_params": r.index_params.model_dump(),
            "ipa_dim": int(ipa.shape[1]), "rpa_dim": int(rpa_dim),
            "ipa_dim_limited_by": None if w_ipa is None else str(w_ipa.cap_reason_),
            "rpa_dim_limited_by": None if w_rpa is None else str(w_rpa.cap_reason_),
            **pooling, **({"retrieval_backbone": backbone} if backbone else {})}, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="build-index", inputs=inputs)
    return out


RPA_FILE = "database_rpa.arrow"  # Arrow IPC: memory-mapped by load_database
LEGACY_RPA_FILE = "database_rpa.parquet"  # databases built before 2026-12-06, still read (into RAM)


def region_offsets_of(image_ids, region_image_ids) -> np.ndarray:
    """`search.region_offsets` on Arrow columns, without making a Python string per region (10^8 of them at
    10^6 images): each region's image position by pyarrow's hash lookup."""
    import pyarrow as pa
    import pyarrow.compute as pc

    owner = pc.index_in(region_image_ids, value_set=pa.chunked_array(image_ids).combine_chunks())
    if owner.null_count:
        raise ValueError("regions of unknown images")
    owner = owner.to_numpy().astype(np.int64, copy=False)
    if np.any(np.diff(owner) < 0):
        raise ValueError("region rows are not grouped by image in the images' order")
    return np.searchsorted(owner, np.arange(len(image_ids) + 1))


SAVED_KINDS = ("hnsw", "ivf_flat", "ivf_pq")  # the first-stage indexes build-index saves (ipa_index.faiss)


def load_database(path: Path, *, index: str | None = None, params=None) -> RetrievalDatabase:
    """The database of `build-index` at `path`, searched with `index` (null: the one it was built with, read
    from its ipa_index.faiss when saved; another kind is built now, with `params`)."""
    from pipeline.retrieval.index import INDEX_FILE, FaissIndex, make_index
    from pipeline.retrieval.search import Database, as_rows
    from pipeline.retrieval.whitening import LearnedWhitening, PCAWhitening, ShrinkageWhitening

    path = Path(path)
    ipa_t = tables.read_table(path / "database_ipa.parquet", "ipa")
    rpa_path = path / (RPA_FILE if (path / RPA_FILE).is_file() else LEGACY_RPA_FILE)
    rpa_t = tables.read_table(rpa_path, "rpa")  # .arrow: memory-mapped, paged in as queries touch regions
    cat = tables.read_table(path / "catalog.parquet", "catalog").to_pydict()
    ids = ipa_t.column("image_id").to_pylist()
    try:
        offsets = region_offsets_of(ipa_t.column("image_id"), rpa_t.column("image_id"))
    except ValueError:
        from pipeline.errors import InputError, Problem

        raise InputError(f"{path}: {rpa_path.name} does not follow database_ipa.parquet's images",
                         [Problem(str(rpa_path), "rows out of order or of unknown images",
                                  fix="re-run `siteloc build-index`")]) from None
    db = Database(ids, np.column_stack([cat["x"], cat["y"], cat["theta"]]), tables.descriptor_matrix(ipa_t),
                  as_rows(tables.descriptor_chunks(rpa_t)), offsets, paged=rpa_path.suffix == ".arrow")
    settings = json.loads((path / "report.json").read_text())
    whitening = {"pca": PCAWhitening, "shrinkage": ShrinkageWhitening, "learned": LearnedWhitening}.get(
        settings["whitening"])
    w_ipa = whitening.load(path / "ipa_whitening.npz") if whitening else None
    w_rpa = PCAWhitening.load(path / "rpa_whitening.npz") if whitening else None
    built = settings.get("index", "exact")
    kind = index or built
    if kind == built and kind in SAVED_KINDS and (path / INDEX_FILE).is_file():
        from pipeline.config import IndexParams

        saved = IndexParams(**settings["index_params"])
        if params is not None:  # search-time settings may change; the build's stay as saved
            saved = saved.model_copy(update={k: getattr(params, k) for k in ("hnsw_ef_search", "ivf_nprobe", "refine")})
        first = FaissIndex.load(path / INDEX_FILE, db.ipa, kind, saved)
    else:
        first = make_index(kind, db.ipa, params)
    return RetrievalDatabase(db, first, w_ipa, w_rpa, settings)


def query_database(rdb: RetrievalDatabase, ipa: np.ndarray, regions: np.ndarray | None, *, top_n: int = 50,
                   weights: tuple[float, ...] = (4, 3, 2, 1), rerank: bool = True):
    """Two-stage retrieval of one image from its raw IPA (D,) and region (Q, Dr) descriptors."""
    from pipeline.retrieval.search import retrieve

    q = ipa[None, :] if rdb.ipa_whitening is None else rdb.ipa_whitening.transform(ipa[None, :])
    reg = None
    if regions is not None and len(regions):
        reg = regions if rdb.rpa_whitening is None else rdb.rpa_whitening.transform(regions)
    return retrieve(rdb.db, rdb.index, q[0], reg, top_n=top_n, weights=weights, rerank_regions=rerank)
