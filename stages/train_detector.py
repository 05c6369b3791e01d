"""`siteloc train-detector`: fine-tune the 9-class Faster R-CNN on an ingested site."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Fine-tune the 9-class Faster R-CNN (8 object classes + background) on an ingested site.

DATA is the output of `siteloc ingest` (images.parquet, boxes.parquet, images/). Training uses the
ingest's train stops minus a seeded share held for validation (detector.val_fraction); the test stops
are left for evaluation. Settings are the `detector` section of the config: backbone (efficientnet_lite0,
the offline CPU default, or vgg16 as in the paper), weights (imagenet, a state-dict file, or null),
image size, iterations, batch size, SGD lr (dropping 10x after detector.lr_drop_at), momentum, weight
decay. Override with --set, e.g. --set detector.iterations=500 --set detector.backbone=vgg16.

Interrupted training resumes from OUT.partial/checkpoint.pt (tensors only) when rerun with the same
arguments. Writes into --out: weights.safetensors, config.json (how to rebuild the model, classes, weights
used), metrics.json (loss curve, validation loss, iterations/s) and config.yaml.

After the building changes (`siteloc update`), --init-from OLD_MODEL fine-tunes an earlier train-detector
output on the updated site instead of starting again from detector.weights: its weights.safetensors is loaded
(tensors only, strictly), and its config.json must name the backbone, image sizes, anchors, NMS and classes this
run builds, else nothing is trained. The frozen layers and batch norms still follow detector.weights (the
weights themselves are not loaded). config.json records init_from (path and sha256 of the weights). It trains
detector.iterations as configured; a short fine-tuning is --set detector.iterations=N.

Example: siteloc train-detector data/reference/ingested --out models/detector

Example: siteloc train-detector data/office/ingested-v2 --out models/detector-v2 --init-from models/detector
"""


def train_detector(
    data: Annotated[Path, typer.Argument(help="An ingested site (output of siteloc ingest).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.", show_default=False)],
    init_from: Annotated[Path | None, typer.Option(
        "--init-from", help="Start from the weights of an earlier `siteloc train-detector` output (a directory with "
        "weights.safetensors and config.json, built with this run's detector settings and classes) instead of "
        "detector.weights.", show_default=False)] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("detector.iterations=3000") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.detection.train import run_train_detector

        cfg = load(config, set_)
        inputs = {"data": data} if init_from is None else {"data": data, "init_from": init_from}
        result = run_train_detector(cfg, inputs=inputs, outputs={"out": out}, force=force, progress=True)
        m = json.loads((result / "metrics.json").read_text())
        c = json.loads((result / "config.json").read_text())
        typer.echo(f"trained {c['builder']['backbone']} ({c['weights_source']}) on {m['train_images']} images: "
                   f"loss {m['loss_first']:.3f} -> {m['loss_last_50_mean']:.3f} (last 50 mean), validation loss "
                   f"{m['val_loss'] if m['val_loss'] is None else round(m['val_loss'], 3)}, "
                   f"{m['iterations_per_s']} it/s")
        echo_path("output", result)
