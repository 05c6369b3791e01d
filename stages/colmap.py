"""`siteloc ingest-colmap MODEL_DIR ...` and `siteloc export-colmap SITE_DIR --out MODEL_DIR`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, ForceOpt, VerboseOpt, cli_errors, load, set_opt

INGEST_HELP = """Turn a COLMAP reconstruction into a site capture directory that `siteloc ingest` accepts.

MODEL_DIR holds cameras, images and points3D (.bin or .txt; rigs and frames when the model has them),
as COLMAP, hloc or `siteloc export-colmap` write them; --images is the folder its image names are
relative to, --map the site's map.yaml. Cameras must be PINHOLE or SIMPLE_PINHOLE (undistort others with
`colmap image_undistorter`).

The model is brought into the map frame by a similarity fitted on --anchors: a CSV of image,x,y,theta
(a captures.csv of another site works too), at least 3 images not on one line. --in-map-frame skips the
fit for a model already in map coordinates with z up. Images are grouped into stops by rig frame, or by
position (ingest.position_tolerance_m); stops without one image per rig view, or with headings that
disagree with the rig, are listed in the report and left out.

--out gets site.yaml (the model's camera, default rig, laser and classes: edit them if yours differ),
map.yaml + map.pgm, captures.csv, images/ (hard links), report.json + report.md (anchor residuals, stops
left out) and config.yaml. Bad input is listed with a fix and nothing is written.

Example: siteloc ingest-colmap colmap/sparse/0 --images colmap/images --map data/office/site/map.yaml
--anchors anchors.csv --out data/office/colmap-site
"""

EXPORT_HELP = """Write a site's views as a posed COLMAP model (cameras, images, rigs, frames; no 3D points).

SITE_DIR is a site capture directory (captures.csv) or the output of `siteloc ingest` (images.parquet).
Each stop becomes one frame of a rig with one PINHOLE camera per view (a COLMAP rig sensor is a camera, so
the cameras share the site's intrinsics); the camera centre is at the stop's position and --camera-height,
the optical axis horizontal along the view's heading. Image names are relative to SITE_DIR/images (or
SITE_DIR when images lie elsewhere): pass that folder to COLMAP or hloc, e.g. to triangulate points from
the known poses.

Example: siteloc export-colmap data/office/site --out data/office/colmap
"""


def ingest_colmap(
    model_dir: Annotated[Path, typer.Argument(help="COLMAP model folder (e.g. sparse/0).", show_default=False)],
    images: Annotated[
        Path, typer.Option("--images", help="Folder the model's image names are relative to.", show_default=False)
    ],
    map_yaml: Annotated[Path, typer.Option("--map", help="The site's map.yaml (ROS map_server).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Site capture directory to write.", show_default=False)],
    anchors: Annotated[
        Path | None,
        typer.Option(
            "--anchors", help="CSV image,x,y,theta of images with known map poses (>= 3).", show_default=False
        ),
    ] = None,
    in_map_frame: Annotated[
        bool, typer.Option("--in-map-frame", help="The model is already in map coordinates with z up: no fit.")
    ] = False,
    name: Annotated[
        str | None, typer.Option("--name", help="Site name \\[default: the output folder's name].", show_default=False)
    ] = None,
    config: ConfigOpt = "demo",
    set_: set_opt("ingest.position_tolerance_m=0.1") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.colmap.ingest import run_ingest_colmap

        cfg = load(config, set_)
        path = run_ingest_colmap(
            cfg,
            inputs={"model": model_dir, "images": images, "map": map_yaml, "anchors": anchors},
            outputs={"out": out},
            force=force,
            in_map_frame=in_map_frame,
            name=name,
        )
        rep = json.loads((path / "report.json").read_text())
        a = rep["alignment"]
        if a["anchors"]:
            pos, head = a["position_error_m"], a["heading_error_deg"]
            head_text = "-" if head["rms"] is None else f"RMS {head['rms']:.3f} deg, max {head['max']:.3f} deg"
            typer.echo(
                f"alignment: {a['method']}, scale {a['scale']:.6g}; {len(a['anchors'])} anchors: position "
                f"RMS {pos['rms']:.4f} m, max {pos['max']:.4f} m; heading {head_text}"
            )
            for r in a["anchors"]:
                h = "-" if r["heading_error_deg"] is None else f"{r['heading_error_deg']:.3f} deg"
                typer.echo(f"  {r['image']}: {r['position_error_m']:.4f} m, {h}")
        else:
            typer.echo(f"alignment: {a['method']}")
        typer.echo(
            f"wrote site '{rep['site']}': {rep['images']} images in {rep['stops']} stops (grouped by "
            f"{rep['grouping']}), {len(rep['stops_left_out'])} stops left out -> {path}"
        )
        for w in rep["warnings"]:
            typer.secho(f"warning: {w}", fg=typer.colors.YELLOW, err=True)


def export_colmap(
    site_dir: Annotated[Path, typer.Argument(help="Site capture directory or ingest output.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="COLMAP model folder to write.", show_default=False)],
    camera_height: Annotated[
        float, typer.Option("--camera-height", help="Height of the camera centres above the floor, metres.")
    ] = 1.2,
    text: Annotated[bool, typer.Option("--text", help="Write the text format (.txt) instead of binary.")] = False,
    config: ConfigOpt = "demo",
    set_: set_opt("ingest.heading_tolerance_deg=5") = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        from pipeline.colmap.export import image_names, read_views, run_export_colmap

        cfg = load(config, set_)
        path = run_export_colmap(
            cfg, inputs={"site": site_dir}, outputs={"out": out}, force=force, camera_height=camera_height, text=text
        )
        site, rows = read_views(site_dir, cfg)
        root, _ = image_names(rows)
        n_stops = len({r.stop_id for r in rows})
        typer.echo(
            f"exported '{site.name}': {len(rows)} images in {n_stops} frames of a {len(site.rig.yaw_offsets)}-camera "
            f"rig, cameras at {camera_height} m -> {path}"
        )
        typer.echo(f"image names are relative to {Path(site_dir) / root}")
