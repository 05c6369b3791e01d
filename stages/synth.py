"""`siteloc synth`: the embedded reference site."""

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
    engine_args,
    load,
)

HELP = """Generate and render a reference office floor as a site capture directory.

The floor (corridor loops, rows of similar rooms, doors, windows, desks, chairs, posters, extinguishers,
bins, plants, exit signs) comes from a preset in configs/sites/ (tiny; office, with the identity cues of
a real building: wings in their colours, room plates, a picture of its own on every poster, escape plans,
signs, notice boards, kitchens, desk clutter, outside views, painted
walls with wing-coloured dados, a pinboard in every room; twins, the same floor without them; paper)
and a seed; the same preset and seed give the same site. Cues switch one by one (--set
identity.room_plates=false), camera realism too (--set camera.effects=realistic, or
--set camera.effects.noise.enabled=true for one effect): docs/reference-site.md.
Views are rendered with OpenGL on a headless EGL context
(Mesa llvmpipe on a CPU) using real furniture meshes and photographic textures from Debian's Sweet Home
3D packages (installed by `make setup`); without them procedural shapes are used, with a warning.

Writes into --out: site.yaml, map.yaml + map.pgm (5 cm), captures.csv and images/ (a stop every ~2 m,
6 views 60 degrees apart), annotations.json (COCO boxes from the instance-id buffer, occlusion-aware),
runs/<run>/ (mapping and query runs: ground truth, noisy odometry, 270-degree laser scans with noise,
dropouts, people and moved chairs, an image per step, kidnappings flagged), contact_sheet.png,
synth_report.json, synth_timing.json, config.yaml and ATTRIBUTION.md. `siteloc ingest` takes the directory as it is.

--change writes the same building after a change (moved furniture, new posters, new notes on the
boards, other lighting; plates and signs stay). --change-area ROOM or ROOM/AREA changes only there (the
lighting stays). --move-wall (implies --change) also moves one interior wall, seeded, by --move-wall-m metres
(0.5): a partition between two rooms, or between a room and the corridor it runs along, never an outer wall
(with --change-area, a wall of those rooms); its doors move with it, furniture in its way is pushed aside or
removed, and map.yaml, the runs' laser scans and the images all show it; synth_report.json's wall_moved names
its rooms and its ends before and after.
--area ROOM or ROOM/AREA captures only the stops there, with the full site's stop ids and all
the runs: the re-capture of changed areas that `siteloc update` merges into a site database.
--config picks the synth section of a preset in configs/ (demo: office; ci: a micro tiny site; paper:
paper) and --preset / --seed / --set override it. --set overrides any site preset key, e.g.
--set camera.width=320 --set camera.height=240 --set runs.query_runs=5.
Every output but synth_timing.json is byte-identical for the same preset, overrides and seed, however
many --workers render (each a process with its own single-threaded EGL context: on 2 cores two of them
render 1.3x faster than one context using both cores), or Ray actors with --engine ray, here or on the
cluster at --ray-address (docs/scaling.md).

Example: siteloc synth --preset office --out data/office/site
"""


def synth(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output capture directory.", show_default=False)],
    preset: Annotated[
        str | None,
        typer.Option(
            "--preset", "-p", show_default=False,
            help="Site preset: tiny, office, twins, paper, or a YAML path \\[default: the config's synth.site].",
        ),
    ] = None,
    seed: Annotated[
        int | None, typer.Option("--seed", help="Seed \\[default: the config's synth.seed].", show_default=False)
    ] = None,
    change: Annotated[
        bool, typer.Option("--change", help="Write the building after an environment change.")
    ] = False,
    change_area: Annotated[
        list[str] | None,
        typer.Option("--change-area", show_default=False,
                     help="Change only this room or room/area (repeatable; implies --change, lighting unchanged)."),
    ] = None,
    move_wall: Annotated[
        bool, typer.Option("--move-wall", help="With the change, also move one interior wall (implies --change).")
    ] = False,
    move_wall_m: Annotated[
        float | None,
        typer.Option("--move-wall-m", min=0.01, show_default=False,
                     help="How far the wall moves, in metres (implies --move-wall) \\[default: 0.5]."),
    ] = None,
    area: Annotated[
        list[str] | None,
        typer.Option("--area", show_default=False,
                     help="Capture only the stops in this room or room/area (repeatable): a re-capture for "
                          "`siteloc update`."),
    ] = None,
    strict_assets: Annotated[
        bool, typer.Option("--strict-assets", help="Fail instead of falling back to procedural shapes.")
    ] = False,
    overrides: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="Override a site preset key, e.g. --set camera.width=320 (repeatable).",
                     rich_help_panel="Configuration"),
    ] = None,
    workers: Annotated[
        int | None, typer.Option("--workers", "-w", min=1, show_default=False,
                                 help="Rendering processes, or Ray actors with --engine ray \\[default: the "
                                      "usable cores, at most 4; 1: this process; on a Ray cluster, its CPUs].")
    ] = None,
    engine: EngineOpt = Executor.LOCAL,
    ray_address: RayAddressOpt = None,
    config: ConfigOpt = "demo",
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.config import parse_overrides
        from pipeline.sitegen.presets import load_site_preset
        from pipeline.sitegen.synth import run_synth

        cfg = load(config, None).synth
        site = load_site_preset(preset or cfg.site, {**cfg.preset_overrides, **parse_overrides(overrides)})
        path = run_synth(site, outputs={"out": out}, seed=cfg.seed if seed is None else seed, change=change,
                         force=force, allow_fallback=not strict_assets, workers=workers, areas=tuple(area or ()),
                         change_areas=tuple(change_area or ()),
                         move_wall_m=move_wall_m if move_wall_m is not None else 0.5 if move_wall else 0.0,
                         **engine_args(engine, ray_address))
        rep = json.loads((path / "synth_report.json").read_text())
        timing = json.loads((path / "synth_timing.json").read_text())
        typer.echo(
            f"synthesised '{rep['site']}': {rep['stops']} stops, {rep['capture_images']} capture images, "
            f"{len(rep['runs'])} runs, {rep['images_rendered']} images at {timing['images_per_s']} images/s "
            f"({timing['render_workers']} rendering processes), {timing['wall_time_s']} s wall -> {path}"
        )
        if "wall_moved" in rep:
            moved = rep["wall_moved"]
            typer.echo(f"moved the wall of {', '.join(moved['rooms'])} by {moved['distance_m']} m into "
                       f"{', '.join(moved['into'])}: {moved['from']} -> {moved['to']}")
        typer.echo("boxes per class: " + ", ".join(f"{c} {n}" for c, n in rep["boxes_per_class"].items()))
        if rep["assets_procedural"]:
            typer.secho(f"warning: procedural shapes for {', '.join(rep['assets_missing'])}", fg="yellow", err=True)
