"""`siteloc demo`: the main job on the shipped data."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, SetOpt, VerboseOpt, cli_errors, load

HELP = """Run the main job end to end on data that ships with the project.

Today this renders the reference site of the config (`synth.site`: office for the demo preset, a
micro site for ci; see `siteloc synth`) and ingests it, ingests every real CARMEN laser log in
../shared/data/carmen (runs table, occupancy map built from the scans, preview PNG; see `siteloc
ingest-log`) and the example capture directory of docs/example-site (see `siteloc ingest`), then
prints a summary. Later versions add detector training, retrieval, the bundle and localization.

Finished steps are reused, so an interrupted demo resumes; --force redoes everything.
Outputs: DATA/reference/site/, DATA/reference/ingested/, DATA/carmen/<log>/, DATA/example/ingested/,
DATA/demo-summary.json.
"""


def demo(
    data: Annotated[Path, typer.Option("--data", "-d", help="Where the outputs go.")] = Path("data"),
    carmen_dir: Annotated[
        Path | None,
        typer.Option(
            "--carmen-dir", help="Folder of CARMEN logs [default: ../shared/data/carmen or $SITELOC_CARMEN_DIR]."
        ),
    ] = None,
    config: ConfigOpt = "demo",
    set_: SetOpt = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from rich.console import Console
        from rich.table import Table

        from pipeline.demo import DEFAULT_CARMEN_DIR, run_demo

        cfg = load(config, set_)
        carmen = carmen_dir or DEFAULT_CARMEN_DIR
        if not carmen.is_dir():
            typer.secho(
                f"warning: no CARMEN logs at {carmen}; only the example site is ingested", fg="yellow", err=True
            )
        steps = run_demo(cfg, inputs={"carmen_dir": carmen}, outputs={"data": data}, force=force)

        table = Table(title="siteloc demo", caption=f"outputs under {data}/ (summary: demo-summary.json)")
        for col in ("step", "input", "map (m)", "endpoints on walls", "status"):
            table.add_column(col)
        for s in steps:
            r = s.report
            if "objects_per_class" in r:
                m = r["map"]
                size = f"{m['width_cells'] * m['resolution']:.1f} x {m['height_cells'] * m['resolution']:.1f}"
                share, count = "-", f"{r['capture_images']} views, {len(r['runs'])} runs"
            elif "scans" in r:
                size = "{:.1f} x {:.1f}".format(*r["map_size_m"])
                share = f"{r['endpoint_on_occupied_share_tol0']:.2f} / {r['endpoint_on_occupied_share_tol1']:.2f}"
                count = f"{r['scans']} x {r['beams']} scans"
            else:
                m = r["map"]
                size = f"{m['width_cells'] * m['resolution']:.1f} x {m['height_cells'] * m['resolution']:.1f}"
                share, count = "-", f"{r['images']} images"
            table.add_row(s.name.removesuffix("-corrected"), count, size, share, "reused" if s.reused else "done")
        Console().print(table)
        typer.echo("endpoints on walls: share of scan endpoints on occupied map cells, exact / within one cell")
