"""`siteloc evaluate-detector`: COCO mAP of a trained detector on the held-out stops of a site."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Score a trained detector on held-out stops: COCO mAP@0.5 and mAP@[.5:.95], overall and per class.

MODEL is the output of `siteloc train-detector`; DATA the ingested site it was trained for. The images
scored are the ingest's `test` split (detector.eval_split): whole stops that neither training nor
validation saw. Scoring is pycocotools' COCOeval (bbox, all areas, 100 detections per image).

Writes into --out: metrics.json (overall and per-class AP, images/s, device), detections.json (COCO
results format, original pixels), predictions.png (held-out views: ground truth dashed, detections with
score >= detector.plot_score labelled) and config.yaml.

Example: siteloc evaluate-detector models/detector data/reference/ingested --out models/detector-eval
"""


def evaluate_detector(
    model: Annotated[Path, typer.Argument(help="A trained detector (output of siteloc train-detector).",
                                          show_default=False)],
    data: Annotated[Path, typer.Argument(help="The ingested site (output of siteloc ingest).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.", show_default=False)],
    config: ConfigOpt = "demo",
    set_: set_opt("detector.plot_score=0.7") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.detection.evaluate import run_evaluate_detector

        cfg = load(config, set_)
        result = run_evaluate_detector(cfg, inputs={"model": model, "data": data}, outputs={"out": out},
                                       force=force, progress=True)
        m = json.loads((result / "metrics.json").read_text())
        typer.echo(f"{m['backbone']} on {m['images']} held-out images ({m['stops']} stops): "
                   f"mAP@0.5 {_fmt(m['map_50'])}, mAP@[.5:.95] {_fmt(m['map_50_95'])}, {m['images_per_s']} img/s")
        width = max(len(n) for n in m["per_class"])
        for name, v in m["per_class"].items():
            typer.echo(f"  {name:<{width}}  AP@0.5 {_fmt(v['ap_50'])}  AP@[.5:.95] {_fmt(v['ap_50_95'])}  "
                       f"({v['gt']} boxes)")
        echo_path("output", result)


def _fmt(v: float | None) -> str:
    return "  n/a" if v is None else f"{v:.3f}"
