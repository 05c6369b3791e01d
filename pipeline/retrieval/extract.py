"""Stage `extract`: IPA and RPA descriptors of every image of an ingested site (seed 000 section 3.1.2).

- IPA (image-wise pooling of activations): the detector's stride-16 map (conv5_3 for `vgg16`), cropped
  to the image so batch padding never counts, summed over positions (`retrieval.pooling: gem`: their
  generalized mean, p `retrieval.gem_p`), l2-normalised.
- RPA (region-wise pooling of activations): per region, each channel's maximum over the cells the box
  touches, l2-normalised. Regions: the `rpa_proposals` best RPN proposals and the detections scoring at
  least `rpa_min_score` (boxes, scores and classes are kept).

`retrieval.backbone` other than `detector` (`pipeline.retrieval.backbones`): the regions still come from
the detector, but IPA and RPA pool that backbone's map of the original image (at its stride), and with a
checkpoint's NetVLAD / GeM head the IPA is the head's output. Both engines support every backbone: the
ONNX graph then holds the detector and the backbone, checked against torch alike. The backbone's record
(name, sizes, weights and their sha256) goes to report.json and the tables' metadata; `build-index`,
`query` and `export` refuse to mix backbones. The pooling goes to report.json (`ipa_pooling`, `gem_p`),
which `build-index` copies; `query` and `export` refuse another pooling than the index's, and the bundle's
describer.json carries it.

On a CPU (`retrieval.engine: auto`) the images are described through onnxruntime: the detector is exported
as the graph the bundle carries (`pipeline.detection.onnx_export`), checked against torch on the first
images of each size (export's tolerances; the report keeps the figures), and run in several threads, so the
database is described by the same graph and the same numpy code as a robot's camera image, 2.7x faster
than eager torch on 2 cores. On a GPU, torch describes batches of `retrieval.batch` images.

Whitening is not applied here: it is fitted on the database by `siteloc build-index`, so one
extraction serves several whitenings. Images: the mapping stops of `images.parquet` and, with
`include_runs`, the camera frames of the runs other than mapping runs (the query images). Work goes in chunks to
`<out>.partial/`; an interrupted extraction resumes from its finished chunks when rerun with the same
model, site and settings, and refuses (naming what differs) otherwise. Each finished chunk is read in full
first and a damaged one computed again (`extract_chunks.discard_damaged_chunks`); `force` starts clean.
With `inputs['reuse']` (an earlier extraction), the rows of images whose content and describer are
unchanged are copied from it (`pipeline.retrieval.reuse`), so an updated site costs only its new images.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, SitelocError
from pipeline.io import tables
from pipeline.retrieval.descriptors import (  # noqa: F401
    GEM_P,
    ImageDescriptors,
    describe_outputs,
    ipa_descriptor,
    pooling_record,
)
from pipeline.retrieval.extract_chunks import ImageRecord, chunk_done, discard_damaged_chunks, write_chunk


def site_images(ingested: Path, *, include_runs: bool) -> list[ImageRecord]:
    """Every image of an ingested site with its pose: mapping stops first, then the frames of the runs
    that are not mapping runs (those are the queries; a mapping run's frames would never be used)."""
    ingested = Path(ingested)
    t = tables.read_table(ingested / "images.parquet", "images").to_pydict()
    out = [ImageRecord(i, x, y, th, s, sp) for i, x, y, th, s, sp in
           zip(t["image_id"], t["x"], t["y"], t["theta"], t["stop_id"], t["split"], strict=True)]
    if include_runs and (ingested / "runs").is_dir():
        for path in sorted((ingested / "runs").glob("*.parquet")):
            if path.stem.startswith("mapping"):
                continue
            r = tables.read_table(path, "runs").select(["run", "image_id", "gt_x", "gt_y", "gt_theta"]).to_pydict()
            for run, image, x, y, th in zip(r["run"], r["image_id"], r["gt_x"], r["gt_y"], r["gt_theta"], strict=True):
                if image and x is not None:
                    out.append(ImageRecord(image, x, y, th, run, f"run:{run}"))
    return out


def describe(det, images: list, rpa_proposals: int, rpa_min_score: float, *,
             backbone=None, pooling: str = "sum", gem_p: float = GEM_P) -> list[ImageDescriptors]:
    """IPA and RPA descriptors of a batch of (3, H, W) images in [0, 1] from one detector pass; with a
    `backbone` (`pipeline.retrieval.backbones.RetrievalBackbone`) pooling its map of each image. The IPA
    pools the map by `pooling` (`descriptors.ipa_descriptor`)."""
    from pipeline.detection.builders import STRIDE
    from pipeline.detection.inference import detector_features

    feats = detector_features(det, images)
    if backbone is None:
        return [describe_outputs(f.feature_map.numpy(), f.scale, STRIDE, f.proposals, f.proposal_scores, f.boxes,
                                 f.scores, f.labels, rpa_proposals=rpa_proposals, rpa_min_score=rpa_min_score,
                                 pooling=pooling, gem_p=gem_p)
                for f in feats]
    maps = backbone.to(det.device).describe_maps(images)
    return [describe_outputs(m, (1.0, 1.0), backbone.stride, f.proposals, f.proposal_scores, f.boxes, f.scores,
                             f.labels, rpa_proposals=rpa_proposals, rpa_min_score=rpa_min_score, global_descriptor=g,
                             pooling=pooling, gem_p=gem_p)
            for f, (m, g) in zip(feats, maps, strict=True)]


def onnx_describer(det, workdir: Path, *, rpa_proposals: int, rpa_min_score: float, samples: int,
                   layout: tuple[int, int] | None = None, backbone=None, pooling: str = "sum", gem_p: float = GEM_P):
    """A `SizedGraphPool` describing image files through the detector's exported ONNX graph (holding the
    retrieval `backbone` too, when given); the IPA pools by `pooling`, which each graph's info (its
    describer.json) records, so the Ray actors pool alike."""
    import torch

    from pipeline.detection.onnx_export import check_parity, export_describer
    from pipeline.onnx_threads import SizedGraphPool
    from pipeline.runtime.describer import describe_with

    def build(hw: tuple[int, int], images: list, path: Path) -> dict:
        meta = export_describer(det, hw, path, backbone=backbone)
        meta.update(rpa_proposals=rpa_proposals, rpa_min_score=rpa_min_score, **pooling_record(pooling, gem_p))
        meta["parity"] = check_parity(det, path, meta, [torch.from_numpy(im) for im in images],
                                      rpa_proposals=rpa_proposals, rpa_min_score=rpa_min_score, backbone=backbone)
        return meta

    return SizedGraphPool("describer", workdir, build, describe_with, samples=samples, layout=layout)


def _fingerprint(model_dir: Path, images: list[ImageRecord], settings: dict) -> str:
    from pipeline.sitegen.asset_cache import sha256_file

    h = hashlib.sha256()
    h.update(sha256_file(Path(model_dir) / "weights.safetensors").encode())
    h.update(json.dumps(settings, sort_keys=True).encode())
    for r in images:
        h.update(r.image_id.encode())
    return h.hexdigest()


def run_extract(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], force: bool = False,
                progress: bool = True, executor: str = "local", ray_address: str | None = None) -> Path:
    """`executor` "ray" describes the chunks on Ray actors (`pipeline.ray_engine`; the same tables as "local")."""

    from pipeline.chunked_encoding import start_partial
    from pipeline.detection.inference import load_detector, load_image
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.progress import progress_bar

    r = cfg.retrieval
    out, ingested, model_dir = Path(outputs["out"]), Path(inputs["data"]), Path(inputs["model"])
    check_output(out, force=force, inputs=inputs.values())
    images = site_images(ingested, include_runs=r.include_runs)
    missing = [i.image_id for i in images if not (ingested / i.image_id).is_file()]
    if missing:
        raise InputError(f"{ingested}: {len(missing)} images are missing",
                         [Problem(str(ingested / m), "file is missing", fix="re-run `siteloc ingest`")
                          for m in missing[:10]])
    from pipeline.onnx_threads import resolve_engine
    from pipeline.retrieval.backbones import load_backbone

    det = load_detector(model_dir, device=r.device)
    backbone = load_backbone(r.backbone, r.backbone_weights)  # None: the detector's own map
    engine = resolve_engine(r.engine, det.device.type)
    settings = {"rpa_proposals": r.rpa_proposals, "rpa_min_score": r.rpa_min_score, "chunk": r.chunk,
                "include_runs": r.include_runs, "engine": engine}
    if backbone is not None:  # (absent for the detector: its fingerprints, and so resumable runs, stay as they were)
        settings["backbone"] = {"name": backbone.name, "weights_sha256": backbone.weights_sha256}
    if r.pooling != "sum":  # (absent for sum, likewise)
        settings["pooling"] = {"name": r.pooling, "p": r.gem_p}
    pooling = {"pooling": r.pooling, "gem_p": r.gem_p}
    fingerprint = _fingerprint(model_dir, images, settings)
    from pipeline.io.image_reuse import HASHES_FILE, image_hashes
    from pipeline.retrieval.reuse import ReusedDescriptors, describer_key
    from pipeline.sitegen.asset_cache import sha256_file

    describer = describer_key(sha256_file(model_dir / "weights.safetensors"), settings)
    sha = image_hashes(ingested, [i.image_id for i in images])
    reuse = ReusedDescriptors(inputs["reuse"], describer, pooling=(r.pooling, r.gem_p)) if inputs.get("reuse") else None
    partial = out.with_name(out.name + ".partial")
    start_partial(partial, fingerprint, len(images), force=force, inputs=inputs.values(),
                  other="an interrupted extraction with another model, site or settings")
    chunks = [images[i:i + r.chunk] for i in range(0, len(images), r.chunk)]
    discard_damaged_chunks(partial, chunks)
    pool = None
    if engine == "onnx":
        from pipeline.onnx_threads import thread_layout

        step = 4 * thread_layout()[0]

        def compute(batch: list[ImageRecord]) -> list[ImageDescriptors]:
            nonlocal pool
            if pool is None:  # made when first needed: an extraction that reuses every image exports no graph
                pool = onnx_describer(det, partial, rpa_proposals=r.rpa_proposals, rpa_min_score=r.rpa_min_score,
                                      samples=cfg.export.parity_images, backbone=backbone, **pooling)
            return pool([ingested / rec.image_id for rec in batch])
    else:
        step = r.batch

        def compute(batch: list[ImageRecord]) -> list[ImageDescriptors]:
            return describe(det, [load_image(ingested / rec.image_id) for rec in batch], r.rpa_proposals,
                            r.rpa_min_score, backbone=backbone, **pooling)
    computed: list[str] = []

    def describe_batch(batch: list[ImageRecord]) -> list[ImageDescriptors]:
        found = [reuse.get(sha[rec.image_id]) if reuse is not None else None for rec in batch]
        todo = [rec for rec, f in zip(batch, found, strict=True) if f is None]
        computed.extend(rec.image_id for rec in todo)
        fresh = iter(compute(todo) if todo else [])
        return [f if f is not None else next(fresh) for f in found]

    where = "onnxruntime, cpu" if engine == "onnx" else det.device.type
    bar = progress_bar(total=len(images), desc=f"extracting ({where})", unit="img", enabled=progress)
    try:
        if executor == "ray":
            if reuse is not None:
                raise SitelocError("--reuse with --engine ray: not supported yet; extract the changed site "
                                   "locally (the default engine), which describes only its new images")
            from pipeline.chunked_encoding import refuse_torch_on_ray
            from pipeline.retrieval.extract_ray import extract_on_ray

            refuse_torch_on_ray(engine, executor, "retrieval.engine")

            pool = onnx_describer(det, partial, rpa_proposals=r.rpa_proposals, rpa_min_score=r.rpa_min_score,
                                  samples=cfg.export.parity_images, backbone=backbone, **pooling)
            computed.extend(extract_on_ray(chunks, partial, ingested, pool, bar, ray_address=ray_address))
        elif executor == "local":
            _extract_chunks(chunks, partial, describe_batch, step, bar)
        else:
            raise ValueError(f"executor must be local or ray, got '{executor}'")
    finally:
        bar.close()
        if pool is not None:
            pool.close()
    def parts(kind: str):  # the chunks one at a time: a site of 10^6 images has ~45 GB of regions
        return (tables.read_table(partial / f"{kind}-{k:05d}.parquet", kind) for k in range(len(chunks)))

    dim = tables.read_table(partial / "ipa-00000.parquet", "ipa").schema.field("descriptor").type.list_size
    meta = {"backbone": det.config["builder"]["backbone"], "model": str(model_dir), "dim": str(dim)}
    record = None
    if backbone is not None:
        record = backbone.record()
        if int(dim) != record["dim"]:
            raise SitelocError(f"{r.backbone}: descriptors of {dim} values, its record says {record['dim']}")
        meta["retrieval_backbone"] = json.dumps(record)
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        rows = {kind: tables.write_table_parts(tmp / f"{kind}.parquet", parts(kind), kind, meta)
                for kind in ("ipa", "rpa")}
        _write_catalog(tmp / "catalog.parquet", images)
        ids = list(dict.fromkeys(i.image_id for i in images))
        tables.write_table(tmp / HASHES_FILE, tables.to_table("image_hashes", {
            "image_id": ids, "sha256": [sha[i] for i in ids]}), "image_hashes")
        write_text_atomic(tmp / "report.json", json.dumps({
            "images": len(images), "stop_images": sum(not i.split.startswith("run:") for i in images),
            "run_images": sum(i.split.startswith("run:") for i in images), "ipa_dim": int(dim),
            "regions": rows["rpa"],
            "backbone": meta["backbone"], "device": str(det.device), "engine": engine,
            **pooling_record(r.pooling, r.gem_p), "describer_sha256": describer,
            # Images described by this run (a resumed run counts only the chunks it finished itself).
            "computed_images": len(computed),
            **({"reuse": {"from": str(inputs["reuse"]), "describer_matches": reuse.matches,
                          "reused_images": len(images) - len(computed),
                          **({"describer_differs": reuse.differs} if reuse.differs else {})}}
               if reuse is not None else {}),
            **({"retrieval_backbone": record} if record else {}),
            # Present when this run exported graphs: a resumed extraction whose chunks are all done has none.
            **({"onnx": {"workers": pool.workers, "threads_per_worker": pool.threads, "graphs": pool.graphs}}
               if pool is not None and pool.graphs else {})}, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="extract", inputs=inputs)
    from pipeline.chunked_encoding import close_partial

    close_partial(partial)
    return out


def _extract_chunks(chunks: list[list[ImageRecord]], partial: Path, describe_batch, step: int, bar) -> None:
    """Describe each chunk not already in `partial` and write its two tables there."""
    for k, chunk in enumerate(chunks):
        if chunk_done(partial, k):
            bar.update(len(chunk))
            continue
        described = []
        for b in range(0, len(chunk), step):
            batch = chunk[b:b + step]
            described.extend(describe_batch(batch))
            bar.update(len(batch))
        write_chunk(partial, k, [rec.image_id for rec in chunk], described)


def _write_catalog(path: Path, images: list[ImageRecord]) -> None:
    columns = {f: [getattr(i, f) for i in images] for f in ("image_id", "x", "y", "theta", "group", "split")}
    tables.write_table(path, tables.to_table("catalog", columns), "catalog")
