"""`siteloc check BUNDLE NEW_DATA --out REPORT`: does a deployed bundle still fit the building?"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Check how well a deployed bundle fits the building as it is now, per room / area.

BUNDLE is the output of `siteloc export` (directory or .tar.gz); NEW_DATA is new captures and/or new
runs of part or all of the floor, ingested (`ingest`, `ingest-bag`, `ingest-colmap`, `ingest-log`, or
`synth --area` for the reference site), in the bundle's map frame.

For the new images: retrieval recall@1 / @4 against the bundle's database and the same-place similarity
(1 for an unchanged view), beside the bundle's own figures at export (its held-out stops); the detector's
mAP@0.5 where the images have boxes. For the new runs' scans at their known poses: the share of scan
endpoints on the bundle's walls, and the square metres of new obstacles and of walls gone. When NEW_DATA
has query runs, the bundle's localization on them (the report of `siteloc evaluate`, in localization/;
--no-localize skips it).

Writes report.json, report.md (a plain recommendation: which areas to re-capture, whether the map needs
updating, whether the detector needs retraining), drift.png (the map, each area tinted by its drift) and
config.yaml. Thresholds: check.* in the config.

Example: siteloc check bundles/office-0.1.0 data/office-now/ingested --out reports/office/check
"""


def check(
    bundle: Annotated[Path, typer.Argument(help="The deployed bundle.", show_default=False)],
    new_data: Annotated[Path, typer.Argument(help="New captures / runs, ingested.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory: the report.", show_default=False)],
    localize: Annotated[bool, typer.Option("--localize/--no-localize", help="Replay the new query runs through "
                                           "the bundle (siteloc evaluate).")] = True,
    config: ConfigOpt = "demo",
    set_: set_opt("check.max_recall_drop=0.3") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.bundle.check import run_check

        path = run_check(load(config, set_), inputs={"bundle": bundle, "data": new_data}, outputs={"out": out},
                         localize=localize, force=force)
        doc = json.loads((path / "report.json").read_text())
        for line in doc["recommendation"]["text"]:
            typer.echo(line)
        echo_path("report", path / "report.md")
        echo_path("picture", path / "drift.png")
