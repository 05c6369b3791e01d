"""`siteloc evaluate-places`: place recognition measured on any place set (real photographs or a site)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, OutOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Measure global image descriptors on a place set: which database image shows the place of each query.

PLACES is a place set (a folder with place_set.yaml, or the yaml itself; docs/data-formats.md#place-sets):
database and query images with the ground truth of which match (a rule such as `aligned: 2` or
`distance_m: 2`, a match matrix such as RTAB-Map's samples_GT.bmp, or a CSV of pairs), or an ingested site
(`siteloc ingest`'s output: database = its train stops, queries = its test stops and every --run-stride-th
run frame, matches within 2 m and 30 deg).

Every combination of --backbone, --pooling, --whitening and --scales is one variant: the images go
through the ImageNet trunk (longest side at most --max-side px), are pooled (sum: the paper's IPA; gem:
generalized mean, p = 3), whitened on the database (none; pca: every dimension the database supports;
shrinkage: regularised by the ratio of dimensions to images, docs/retrieval.md#whitening) and ranked by
cosine similarity. --scales 1/2 describes each image at 1x and 2x and sums the two. With --detector (a
`siteloc train-detector` output) each one-scale variant is also re-ranked as the paper's second stage: its
Top-N (retrieval.top_n) by RPA, the backbone's map max-pooled over the detector's proposals and detections
(`+rpa` in the table).

Writes into --out: report.md (R@1/5/10, mAP@4, dimensions and milliseconds per image of each variant,
beside the baseline: sum pooling, no whitening, one scale), metrics.json, misses.png (the queries whose
Top-1 is wrong under the best variant, with that Top-1 and the first true match), config.yaml.

Example: siteloc evaluate-places ../shared/data/real-images/vpr-bench-corridor --out reports/places/vpr
--backbone lite0_s16 --backbone lite0_s32 --scales 1 --scales 1/2
"""


def evaluate_places(
    places: Annotated[Path, typer.Argument(help="A place set (folder with place_set.yaml, or the yaml) or an "
                                           "ingested site.", show_default=False)],
    out: OutOpt,
    backbone: Annotated[list[str] | None, typer.Option(
        "--backbone", help="A retrieval backbone (repeatable) \\[default: lite0_s16, lite0_s32].")] = None,
    pooling: Annotated[list[str] | None, typer.Option(
        "--pooling", help="sum or gem (repeatable) \\[default: both].")] = None,
    whitening: Annotated[list[str] | None, typer.Option(
        "--whitening", help="none, pca or shrinkage (repeatable) \\[default: all three].")] = None,
    scales: Annotated[list[str] | None, typer.Option(
        "--scales", help="Scales of one variant, joined by / (repeatable), e.g. 1/2 \\[default: 1].")] = None,
    max_side: Annotated[int, typer.Option("--max-side", min=0, help="Shrink images whose longest side is longer "
                                          "(pixels; 0: as recorded).")] = 640,
    run_stride: Annotated[int, typer.Option("--run-stride", min=1, help="With an ingested site: every Nth run "
                                            "frame is a query.")] = 10,
    detector: Annotated[Path | None, typer.Option(
        "--detector", help="A `siteloc train-detector` output: also re-rank each one-scale variant's Top-N by RPA "
        "over the detector's regions.", show_default=False)] = None,
    weights: Annotated[list[str] | None, typer.Option(
        "--weights", help="BACKBONE=FILE: that backbone's weights from a local file (repeatable).")] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("retrieval.backbone=lite0_s32") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from pipeline.errors import ConfigError
        from pipeline.retrieval.place_eval import POOLINGS, WHITENINGS, run_evaluate_places

        for given, allowed, what in ((pooling, POOLINGS, "--pooling"), (whitening, WHITENINGS, "--whitening")):
            bad = sorted(set(given or ()) - set(allowed))
            if bad:
                raise ConfigError(f"{what} {', '.join(bad)}: expected one of {', '.join(allowed)}")
        from pipeline.retrieval.backbones import BACKBONES

        named = [b for b in BACKBONES if b != "detector"]
        bad = sorted(set(backbone or ()) - set(named))
        if bad:
            raise ConfigError(f"--backbone {', '.join(bad)}: expected one of {', '.join(named)} (the detector's trunk "
                              "is measured by evaluate-retrieval on a site)")
        scale_sets = []
        for text in scales or ["1"]:
            try:
                sc = tuple(float(v) for v in text.split("/"))
            except ValueError:
                raise ConfigError(f"--scales {text!r}: numbers joined by /, e.g. 1/2") from None
            if not all(0.1 <= s <= 4.0 for s in sc):
                raise ConfigError(f"--scales {text!r}: each scale between 0.1 and 4")
            scale_sets.append(sc)
        result = run_evaluate_places(
            load(config, set_), inputs={"places": places, "detector": detector}, outputs={"out": out},
            backbones=backbone or ["lite0_s16", "lite0_s32"], poolings=pooling or list(POOLINGS),
            whitenings=whitening or list(WHITENINGS), scales=scale_sets, max_side=max_side or None,
            weights=_weights(weights), run_stride=run_stride, force=force, progress=sys.stderr.isatty())
        typer.echo((result / "report.md").read_text())
        echo_path("output", result)


def _weights(values: list[str] | None) -> dict[str, str]:
    from pipeline.errors import ConfigError

    out = {}
    for v in values or []:
        name, sep, path = v.partition("=")
        if not sep or not name or not path:
            raise ConfigError(f"--weights {v!r}: expected BACKBONE=FILE, e.g. lite0_s32=weights/lite0.safetensors")
        out[name] = path
    return out
