"""`siteloc ingest SITE_DIR --out DIR`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, load, set_opt

HELP = """Validate a site capture directory and write the normalised site database.

SITE_DIR holds site.yaml, map.yaml + map.pgm, captures.csv, images/, and optionally annotations.json
(COCO boxes) and runs/<run>/ (trajectory.csv + scans.npy); the format is in docs/capture-format.md.

Everything is checked before anything is written: missing or unreadable images, duplicate ids, NaN
or out-of-map poses, poses inside walls, stops with the wrong views, headings that disagree with the
rig, boxes outside the image or of unknown classes, broken map files, bad runs. Every problem is
listed with its file and line, and the command exits 1 leaving no output.

On success --out holds images.parquet, boxes.parquet, runs/*.parquet, map.yaml + map.pgm,
site.yaml, images/ (hard links), report.json + report.md and config.yaml (the effective config).
Stops are split into train/test as whole stops, seeded (ingest.split in the config).

Example: siteloc ingest data/office/site --out data/office/ingested
"""


def ingest(
    site_dir: Annotated[Path, typer.Argument(help="Site capture directory (holds site.yaml).", show_default=False)],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Output directory for the ingested site.", show_default=False)
    ],
    config: ConfigOpt = "demo",
    set_: set_opt("ingest.split.seed=3") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from pipeline.ingest import run_ingest

        cfg = load(config, set_)
        path = run_ingest(cfg, inputs={"site": site_dir}, outputs={"out": out}, force=force)
        import json

        rep = json.loads((path / "report.json").read_text())
        typer.echo(
            f"ingested '{rep['site']}': {rep['images']} images in {rep['stops']} stops "
            f"({', '.join(f'{n} {s}' for s, n in rep['stops_per_split'].items())}), {rep['boxes']} boxes, "
            f"{len(rep['runs'])} runs -> {path}"
        )
        for w in rep["warnings"]:
            typer.secho(f"warning: {w}", fg=typer.colors.YELLOW, err=True)
