"""`siteloc extract`, `build-index`, `query`, `evaluate-retrieval`: coarse place recognition."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import (
    ConfigOpt,
    EngineOpt,
    Executor,
    ForceOpt,
    OutOpt,
    RayAddressOpt,
    VerboseOpt,
    cli_errors,
    echo_path,
    engine_args,
    load,
    set_opt,
)

EXTRACT_HELP = """Extract IPA and RPA descriptors of every image of an ingested site with a trained detector.

MODEL is the output of `siteloc train-detector`, DATA the ingested site. IPA: the detector's stride-16
map (conv5_3 for vgg16) cropped to the image, sum-pooled, l2-normalised. RPA: per region (the
retrieval.rpa_proposals best RPN proposals and the detections scoring >= retrieval.rpa_min_score), each
channel's maximum over the region, l2-normalised; boxes, scores and classes are kept. Images: the mapping
stops and, with retrieval.include_runs, the runs' camera frames. Whitening comes later (build-index).
With --reuse EARLIER_EXTRACTION, images whose sha256 and describer (detector weights, backbone, engine,
RPA settings) are unchanged take their rows from it: the output is the one a full run writes.

Work goes in chunks of retrieval.chunk images to OUT.partial/; rerunning an interrupted extraction with
the same model, site and settings resumes it, with either engine. --engine ray describes the chunks on Ray
actors, here or on the cluster at --ray-address: the same tables (docs/scaling.md). Writes ipa.parquet,
rpa.parquet (descriptor: fixed_size_list<float32>), catalog.parquet (poses), report.json, config.yaml.

Example: siteloc extract models/detector data/reference/ingested --out data/reference/descriptors
"""

INDEX_HELP = """Fit the whitening on the database images and write the retrieval database the runtime queries.

DESCRIPTORS is the output of `siteloc extract`. The database is its `train` stops. retrieval.whitening:
pca (PCA-whitening, the paper's), learned (supervised, from image pairs within retrieval.pair_distance m
and retrieval.pair_heading_deg degrees, Radenovic et al. 2016) or none. The dimension is capped by what
the data supports (report.json says which limit applied). Writes database_ipa.parquet,
database_rpa.arrow, catalog.parquet, ipa_whitening.npz, rpa_whitening.npz (arrays, no pickles),
report.json, config.yaml.

Example: siteloc build-index data/reference/descriptors --out data/reference/index
"""

QUERY_HELP = """Localize images coarsely: IPA Top-N, RPA re-ranking, Top-4 candidate poses with weights 4:3:2:1.

INDEX is the output of `siteloc build-index`, --model the detector the descriptors came from. Prints,
per image, the candidates (database image, pose, weight) and with --out writes them as JSON.

Example: siteloc query data/reference/index --model models/detector photo.jpg
"""

EVALUATE_HELP = """Measure retrieval on held-out queries: IPA only vs IPA + RPA re-ranking, for each whitening.

DESCRIPTORS is the output of `siteloc extract`; DATA the ingested site (for the example pictures).
Database: the train stops; queries: the test stops and the frames of the non-mapping runs. Writes
metrics.json (mAP@4 and recall@{1,4,10,50} with positives within {1,2,5} m and {30,60} degrees, for
none / PCA / learned whitening), report.md (the table, beside the paper's mAP@4 of 0.742), recall.png
and examples.png (queries with their Top-4, green when within 2 m and 30 degrees), config.yaml.

With --queries D2 --queries-data DATA2 the queries come from another extraction (the test stops and
query runs of the building after `siteloc synth --change`, say) against the same database.

Example: siteloc evaluate-retrieval data/reference/descriptors data/reference/ingested --out reports/retrieval
"""


TRAIN_PLACE_HELP = """Train a place-recognition network (trunk + NetVLAD / GeM head) on a site's own geo-tagged images.

DATA is an ingested site. The database views and every place.frame_stride-th mapping-run frame train it;
the last mapping run is held out (place.validation_run) to pick the epoch by its recall@1 against the
database views. Positives lie within place.positive_m and place.positive_heading_deg (the evaluation's
2 m / 30 deg) and come from another stop or run; hard negatives (beyond place.negative_m or
place.negative_heading_deg) are re-mined from every image's descriptor each epoch; the loss is NetVLAD's
triplet margin. The ImageNet trunk (place.trunk) is frozen but for its last place.tune_blocks blocks
(default 0: the head alone); its frozen part runs once per image and is cached (about 9 min for 2190
images on 2 cores), then an epoch of the head takes about a minute. place.tune_blocks=1 learns better
(held-out recall@1 0.61 against 0.53 on the office) but takes about 30 min an epoch on 2 cores: use it on
a GPU (seconds an epoch; place.device=auto picks one).

Writes place.safetensors, metrics.json (loss and held-out recall per epoch), training.png, config.yaml.
Use it with `--set retrieval.backbone=checkpoint --set retrieval.backbone_weights=OUT/place.safetensors`
in `extract` (IPA is then the head's descriptor; RPA pools the tuned trunk's map over the detector's
regions). Checkpoints after every epoch; an interrupted training resumes when rerun.

Example: siteloc train-place data/reference/ingested --out models/place
"""


def extract(
    model: Annotated[Path, typer.Argument(help="A trained detector.", show_default=False)],
    data: Annotated[Path, typer.Argument(help="The ingested site.", show_default=False)],
    out: OutOpt,
    reuse: Annotated[Path | None, typer.Option(
        "--reuse", show_default=False,
        help="An earlier extraction: images whose content is unchanged, described by the same detector and "
             "settings, take their rows from it (after `siteloc update`).")] = None,
    engine: EngineOpt = Executor.LOCAL,
    ray_address: RayAddressOpt = None,
    config: ConfigOpt = "demo",
    set_: set_opt("retrieval.chunk=32") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.retrieval.extract import run_extract

        executor = engine_args(engine, ray_address)
        cfg = load(config, set_)
        inputs = {"model": model, "data": data, **({"reuse": reuse} if reuse is not None else {})}
        result = run_extract(cfg, inputs=inputs, outputs={"out": out}, force=force, **executor)
        r = json.loads((result / "report.json").read_text())
        typer.echo(f"extracted {r['images']} images ({r['stop_images']} stop views, {r['run_images']} run frames): "
                   f"IPA {r['ipa_dim']}-d, {r['regions']} RPA regions ({r['backbone']}, {r['device']})")
        if "reuse" in r:
            u = r["reuse"]
            why = "" if u["describer_matches"] else " (another detector or other settings: nothing could be reused)"
            typer.echo(f"reused {u['reused_images']} images from {u['from']}, described {r['computed_images']}{why}")
        echo_path("output", result)


def build_index(
    descriptors: Annotated[Path, typer.Argument(help="Output of siteloc extract.", show_default=False)],
    out: OutOpt,
    config: ConfigOpt = "demo",
    set_: set_opt("retrieval.whitening=learned") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.retrieval.database import run_build_index

        cfg = load(config, set_)
        result = run_build_index(cfg, inputs={"descriptors": descriptors}, outputs={"out": out}, force=force)
        r = json.loads((result / "report.json").read_text())
        typer.echo(f"database of {r['images']} images, {r['regions']} regions, whitening {r['whitening']}: IPA "
                   f"{r['ipa_dim']}-d (limited by {r['ipa_dim_limited_by']}), RPA {r['rpa_dim']}-d")
        echo_path("output", result)


def query(
    index: Annotated[Path, typer.Argument(help="Output of siteloc build-index.", show_default=False)],
    images: Annotated[list[Path], typer.Argument(help="Image files to localize.", show_default=False)],
    model: Annotated[Path, typer.Option("--model", help="The detector the database was extracted with.",
                                        show_default=False)],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the candidates as JSON here.")] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("retrieval.top_n=100") = None,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        import numpy as np

        from pipeline.detection.inference import load_detector, load_image
        from pipeline.errors import InputError, Problem
        from pipeline.io.atomic import write_text_atomic
        from pipeline.io.images import ImageError, open_image
        from pipeline.retrieval.database import load_database, query_database
        from pipeline.retrieval.extract import describe

        r = load(config, set_).retrieval
        bad = [p for p in images if not p.is_file()]
        if bad:
            raise InputError("images not found", [Problem(str(p), "no such file") for p in bad])
        unreadable = []
        for path in images:  # decoded once before the index and the detector load: every bad image named at once
            try:
                open_image(path)
            except ImageError as exc:
                unreadable.extend(exc.problems)
        if unreadable:
            raise InputError("images that cannot be read; nothing was queried", unreadable)
        from pipeline.retrieval.backbones import check_backbone, load_backbone, recorded_backbone

        rdb = load_database(index, index=r.index, params=r.index_params)
        det = load_detector(model, device=r.device)
        backbone = load_backbone(r.backbone, r.backbone_weights)  # the one the index was extracted with, or refused
        check_backbone(recorded_backbone(index), backbone, index)
        from pipeline.retrieval.descriptors import check_pooling

        check_pooling(index / "report.json", r.pooling, r.gem_p)  # the index's IPA pooling, or refused
        answers = {}
        for path in images:
            d = describe(det, [load_image(path)], r.rpa_proposals, r.rpa_min_score, backbone=backbone,
                         pooling=r.pooling, gem_p=r.gem_p)[0]
            res = query_database(rdb, d.ipa, d.rpa[d.query_rows(r.query_regions)], top_n=r.top_n,
                                 weights=tuple(r.candidate_weights), rerank=r.rerank)
            answers[str(path)] = [{"image_id": rdb.db.image_ids[int(i)], "x": float(c[0]), "y": float(c[1]),
                                   "theta_deg": float(np.degrees(c[2])), "weight": float(c[3])}
                                  for i, c in zip(res.ranked, res.candidates, strict=False)]
            typer.echo(f"{path}:")
            for k, a in enumerate(answers[str(path)]):
                typer.echo(f"  #{k + 1}  x {a['x']:7.2f}  y {a['y']:7.2f}  theta {a['theta_deg']:7.1f} deg  "
                           f"weight {a['weight']:.2f}  ({a['image_id']})")
        if out:
            write_text_atomic(out, json.dumps(answers, indent=2) + "\n")
            echo_path("output", out)


def evaluate_retrieval(
    descriptors: Annotated[Path, typer.Argument(help="Output of siteloc extract.", show_default=False)],
    data: Annotated[Path, typer.Argument(help="The ingested site (for example pictures).", show_default=False)],
    out: OutOpt,
    queries: Annotated[Path | None, typer.Option(
        "--queries", help="Take the queries from this other extraction (e.g. of the site after synth --change); "
        "the database stays DESCRIPTORS' train stops.")] = None,
    queries_data: Annotated[Path | None, typer.Option(
        "--queries-data", help="The ingested site of --queries (for its pictures).")] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("retrieval.query_regions=20") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from pipeline.errors import ConfigError
        from pipeline.retrieval.evaluate import run_evaluate_retrieval

        if (queries is None) != (queries_data is None):
            raise ConfigError("--queries and --queries-data go together: the other extraction and its ingested site")
        cfg = load(config, set_)
        inputs = {"descriptors": descriptors, "data": data}
        if queries is not None:
            inputs |= {"query_descriptors": queries, "query_data": queries_data}
        result = run_evaluate_retrieval(cfg, inputs=inputs, outputs={"out": out}, force=force)
        typer.echo((result / "report.md").read_text())
        echo_path("output", result)


def train_place(
    data: Annotated[Path, typer.Argument(help="The ingested site.", show_default=False)],
    out: OutOpt,
    config: ConfigOpt = "demo",
    set_: set_opt("place.epochs=10") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.retrieval.train_place import run_train_place

        result = run_train_place(load(config, set_), inputs={"data": data}, outputs={"out": out}, force=force)
        m = json.loads((result / "metrics.json").read_text())
        typer.echo(f"{m['images']} images ({m['database_views']} database views, {m['run_frames']} run frames, "
                   f"{m['validation_frames']} held out), {m['anchors']} anchors, {m['descriptor_dim']}-d, "
                   f"{m['device']}: cache {m['cache_seconds']:.0f} s, training {m['train_seconds']:.0f} s")
        for h in m["history"]:
            v = h["validation"]
            held = f"held-out recall@1 {v['recall_at_1']:.3f}, mAP@4 {v['map_at_4']:.3f}" if v else "no held-out run"
            loss = "" if h["loss"] is None else f"loss {h['loss']:.4f}, "
            typer.echo(f"  epoch {h['epoch']}: {loss}{held}" + ("  (kept)" if h["epoch"] == m["kept_epoch"] else ""))
        echo_path("checkpoint", result / "place.safetensors")
