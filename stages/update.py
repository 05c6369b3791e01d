"""`siteloc update SITE_DB NEW_DATA --out DIR`: a site database brought up to date with new captures."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, echo_path, load, set_opt

HELP = """Update a site database after the building changed, from new captures of the changed areas only.

SITE_DB is the database in use (the --out of `ingest` or of an earlier `update`); NEW_DATA is the new
captures, ingested the same way (`ingest`, `ingest-colmap`, `ingest-bag`, or `synth --areas` for the
reference site). They must share the site's camera, rig, laser, classes and map frame.

Every new stop replaces all old stops of its area: by its room/area labels, or, without labels, the area
of the nearest old stop within update.proximity_m. --remove-stop drops stops explicitly. The other
stops keep their rows, boxes and image files exactly. New runs are added (a run of the same name replaces
the old one; --remove-run drops one). The map is patched from the new runs' scans with ground-truth
poses, in the changed areas only (each map cell belongs to the area of its nearest stop along the free space).

Writes the updated database (the files `ingest` writes) plus changelog.json / changelog.md (stops
removed and added per area, runs, map cells changed, the parent's checksums) and map_patch.png (the
changed areas tinted, cells now occupied red, freed green). Nothing is written when an input is wrong.

Example: siteloc update data/office/ingested data/office-wing-b/ingested --out data/office/ingested-v2
"""

StopsOpt = Annotated[list[str] | None, typer.Option("--remove-stop", help="A stop_id to drop (repeatable).",
                                                   show_default=False)]
RunsOpt = Annotated[list[str] | None, typer.Option("--remove-run", help="A run to drop (repeatable).",
                                                  show_default=False)]


def update(
    site_db: Annotated[Path, typer.Argument(help="The site database in use.", show_default=False)],
    new_data: Annotated[Path, typer.Argument(help="The new captures, ingested.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory: the updated database.",
                                      show_default=False)],
    remove_stop: StopsOpt = None,
    remove_run: RunsOpt = None,
    allow_new_areas: Annotated[bool, typer.Option("--allow-new-areas", help="Accept labelled areas the database "
                                                  "does not have (a new part of the building).")] = False,
    config: ConfigOpt = "demo",
    set_: set_opt("update.proximity_m=3") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.update.site_update import run_update

        path = run_update(load(config, set_), inputs={"site_db": site_db, "new_data": new_data},
                          outputs={"out": out}, remove_stops=remove_stop, remove_runs=remove_run,
                          allow_new_areas=allow_new_areas, force=force)
        c = json.loads((path / "changelog.json").read_text())
        t, m = c["totals"], c["map"]
        typer.echo(f"areas changed: {', '.join(c['changed_areas']) or 'none'}; kept {t['stops_kept']} stops "
                   f"untouched, added {t['stops_added']}; map: {m['cells_changed']} cells changed from "
                   f"{m['scans_used']} scans")
        echo_path("changelog", path / "changelog.md")
        echo_path("output", path)
