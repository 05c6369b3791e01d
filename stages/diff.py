"""`siteloc diff BUNDLE_A BUNDLE_B`: what changed between two bundles of a site."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load

HELP = """Say what changed from BUNDLE_A to BUNDLE_B (two exports of one site, directories or .tar.gz).

Stops kept, added, removed and re-captured per room / area (a stop is fingerprinted by its images'
sha256), map cells changed per area, which inputs (detector, database, ingest, sequence model, area
prior) were retrained or kept, and which bundle files differ. `export --parent` ships the same comparison
as the new bundle's changelog.

With --data (an ingested site), both bundles' retrieval recall@1 / @4, same-place similarity and detector
mAP@0.5 on its images, per area, side by side. With --out, diff.json and diff.md are written there.

Example: siteloc diff bundles/office-0.1.0 bundles/office-0.1.1 --data data/office-now/ingested
"""


def diff(
    bundle_a: Annotated[Path, typer.Argument(help="The older bundle.", show_default=False)],
    bundle_b: Annotated[Path, typer.Argument(help="The newer bundle.", show_default=False)],
    data: Annotated[Path | None, typer.Option("--data", help="An ingested site both bundles are measured on.",
                                              show_default=False)] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write diff.json and diff.md here.",
                                             show_default=False)] = None,
    config: ConfigOpt = "demo",
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from pipeline.bundle.diff import run_diff

        d = run_diff(load(config, []), inputs={"a": bundle_a, "b": bundle_b, "data": data},
                     outputs={"out": out} if out else {}, force=force)
        typer.echo(d["markdown"].rstrip())
        if out:
            echo_path("diff", Path(out) / "diff.md")
