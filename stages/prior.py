"""`siteloc prior ...`: seed 001's area prior from a pretrained CNN's layers (no training)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import (
    ConfigOpt,
    EngineOpt,
    Executor,
    ForceOpt,
    OutOpt,
    RayAddressOpt,
    VerboseOpt,
    cli_errors,
    echo_path,
    engine_args,
    help_text,
    load,
    set_opt,
)

APP_HELP = """Room-and-area localization from pretrained multi-layer CNN features (seed 001).

Three layers of a pretrained network (AlexNet pool5/fc6/fc7 as the paper, VGG16, or the offline
EfficientNet-Lite0's pool/head/logits: prior.backbone) describe each capture image; each layer is
compressed to 128-d (prior.compression: ipca, kpca, srp, grp or none), indexed in a ball tree with its
(room, area) label, and a Gaussian is fitted per class. A query's k=10 neighbours per layer are scored
by Spearman or Pearson correlation (or the Gaussians, prior.measure) and the layers mixed by
prior.layer_weights. New areas are appended without refitting anything else.

Steps: features -> build -> (append / update) -> query / evaluate.
"""

FEATURES_HELP = """Compute the three layers' vectors of every capture image of an ingested site.

DATA is the output of `siteloc ingest`; every image needs room and area labels. Writes one Parquet file
per layer (<layer>.parquet: image_id, stop, room, area, split, pose, l2-normalised vector), report.json
and config.yaml. On a CPU the network runs as the ONNX graph the bundle carries (prior.engine: auto),
checked against torch first. Work goes in chunks of prior.chunk images to OUT.partial/, so an interrupted
run resumes; --engine ray encodes the chunks on Ray actors: the same vectors (docs/scaling.md).

Example: siteloc prior features data/reference/ingested --out data/reference/multilayer
"""

BUILD_HELP = """Build the model database: compress, index and model each (room, area) class.

FEATURES is the output of `siteloc prior features`. The database is the `train` split (--all: every
image). Writes prior.json, per layer <layer>_compression.npz, <layer>_gaussians.npz and db_<layer>.parquet,
report.json (memory per layer) and config.yaml; no pickles, the ball trees are rebuilt on load.

Example: siteloc prior build data/reference/multilayer --out models/prior
"""

APPEND_HELP = """Append a new area's images to a prior, without refitting the compressions or other classes.

FEATURES is a `siteloc prior features` output of the new images (same config as the prior); --room
keeps only the named rooms. Writes a new prior directory (--out); the old one is left as it is.

Example: siteloc prior append models/prior data/wing-b/multilayer --room R40 --out models/prior-wing-b
"""

UPDATE_HELP = """Bring a prior to the images of an updated site, refitting only the classes that changed.

FEATURES is a `siteloc prior features` output of the site after `siteloc update` (same config as the
prior; --reuse the prior's features there so that only new images are encoded). An image is the same
when its id and sha256 are: the prior's rows of images gone or re-captured are dropped, the new images
compressed with the fitted compressions and added, and the Gaussians of the classes that lost or got
images refitted; a class left without images goes. Everything else is kept bit for bit. Writes a new
prior directory (--out); report.json lists what changed under `updated`.

Example: siteloc prior update models/prior data/office/multilayer-v2 --out models/prior-v2
"""

QUERY_HELP = """Print the most probable (room, area) classes of camera images.

Example: siteloc prior query models/prior data/reference/ingested/images/stop0003_v2.jpg
"""

EVALUATE_HELP = """Reproduce seed 001's experiments on a site: Table I, layer weights x measure, seeding.

FEATURES is a `siteloc prior features` output: database = its train split, queries = the held-out stops.
--changed adds queries from the site after `synth --change` (its own features). --bundle with --data (the
ingested site with query runs) compares seeding the filter from the area prior, from the Top-4 retrieved
poses and uniformly, in steps to converge on the same runs (with the bundle's own prior and ONNX encoder
when it was exported with --prior). It also measures appending: a prior built without every fifth room,
then their images appended. Writes metrics.json, report.md, table_one.png, layer_weights.png,
examples.png, seeding.png and config.yaml.

Example: siteloc prior evaluate data/reference/multilayer --bundle bundles/office-0.1.0
--data data/reference/ingested --out reports/office/prior
"""

app = typer.Typer(help=help_text(APP_HELP), no_args_is_help=True, add_completion=False,
                  context_settings={"help_option_names": ["-h", "--help"]})


@app.command("features", help=help_text(FEATURES_HELP))
def features(
    data: Annotated[Path, typer.Argument(help="An ingested site.", show_default=False)],
    out: OutOpt,
    reuse: Annotated[Path | None, typer.Option(
        "--reuse", help="An earlier `prior features` output: images it encoded (same bytes, same encoder) are "
        "copied, only the others computed (after `siteloc update`).", show_default=False)] = None,
    config: ConfigOpt = "demo", set_: set_opt("prior.batch=32") = None,
    engine: EngineOpt = Executor.LOCAL, ray_address: RayAddressOpt = None,
    force: ForceOpt = False, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.prior.features import run_prior_features

        executor = engine_args(engine, ray_address)
        path = run_prior_features(load(config, set_), inputs={"data": data, **({"reuse": reuse} if reuse else {})},
                                  outputs={"out": out}, force=force, **executor)
        r = json.loads((path / "report.json").read_text())
        typer.echo(f"{r['images']} images, {r['classes']} (room, area) classes; layers "
                   + ", ".join(f"{k} {v}-d" for k, v in r["dims"].items()) + f" ({r['encoder']['weights']}); "
                   f"computed {r['computed_images']}" + (f", reused {r['reuse']['reused_images']}" if "reuse" in r
                                                         else ""))
        echo_path("features", path)


@app.command("build", help=help_text(BUILD_HELP))
def build(
    features_dir: Annotated[Path, typer.Argument(metavar="FEATURES", help="`prior features` output.",
                                                 show_default=False)],
    out: OutOpt,
    all_images: Annotated[bool, typer.Option("--all", help="Every image, not only the train split.")] = False,
    config: ConfigOpt = "demo", set_: set_opt("prior.compression=ipca") = None,
    force: ForceOpt = False, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.prior.build import run_prior_build

        path = run_prior_build(load(config, set_), inputs={"features": features_dir}, outputs={"out": out},
                               all_images=all_images, force=force)
        r = json.loads((path / "report.json").read_text())
        typer.echo(f"{r['images']} images, {r['classes']} classes; " + ", ".join(
            f"{n} {c['kind']} {c['dims']}-d, {r['memory_kb'][n]:.0f} KB" for n, c in r["compression"].items()))
        echo_path("prior", path)


@app.command("append", help=help_text(APPEND_HELP))
def append(
    prior: Annotated[Path, typer.Argument(help="A `prior build` output.", show_default=False)],
    features_dir: Annotated[Path, typer.Argument(metavar="FEATURES", help="Features of the new images.",
                                                 show_default=False)],
    out: OutOpt,
    room: Annotated[list[str] | None, typer.Option("--room", help="Only these rooms (repeatable).")] = None,
    config: ConfigOpt = "demo", set_: set_opt("prior.seed=1") = None,
    force: ForceOpt = False, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.prior.build import run_prior_append

        path = run_prior_append(load(config, set_), inputs={"prior": prior, "features": features_dir},
                                outputs={"out": out}, rooms=room, force=force)
        a = json.loads((path / "report.json").read_text())["appended"][-1]
        typer.echo(f"appended {a['images']} images: {a['new_classes']} new classes, "
                   f"{a['refitted_classes']} known classes refitted")
        echo_path("prior", path)


@app.command("update", help=help_text(UPDATE_HELP))
def update(
    prior: Annotated[Path, typer.Argument(help="A `prior build` output.", show_default=False)],
    features_dir: Annotated[Path, typer.Argument(metavar="FEATURES", help="Features of the updated site.",
                                                 show_default=False)],
    out: OutOpt,
    config: ConfigOpt = "demo", set_: set_opt("prior.seed=1") = None,
    force: ForceOpt = False, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.prior.build import run_prior_update

        path = run_prior_update(load(config, set_), inputs={"prior": prior, "features": features_dir},
                                outputs={"out": out}, force=force)
        u = json.loads((path / "report.json").read_text())["updated"][-1]
        typer.echo(f"kept {u['kept']} images, dropped {u['dropped']}, added {u['added']}: "
                   f"{len(u['refitted_classes'])} classes refitted, {len(u['new_classes'])} new, "
                   f"{len(u['removed_classes'])} removed")
        echo_path("prior", path)


@app.command("query", help=help_text(QUERY_HELP))
def query(
    prior: Annotated[Path, typer.Argument(help="A `prior build` output.", show_default=False)],
    images: Annotated[list[Path], typer.Argument(help="Camera images.", show_default=False)],
    top: Annotated[int, typer.Option("--top", min=1, help="Classes to print per image.")] = 3,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
    config: ConfigOpt = "demo", set_: set_opt("prior.weights=models/lite0.pt") = None, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        import json

        from pipeline.prior.build import query_images

        found = query_images(load(config, set_), prior, images, top)
        if as_json:
            typer.echo(json.dumps(found, indent=2))
            return
        for f in found:
            typer.echo(f["image"] + ": " + ", ".join(f"{a['room']}/{a['area']} {a['probability']:.3f}"
                                                       for a in f["areas"]))


@app.command("evaluate", help=help_text(EVALUATE_HELP))
def evaluate(
    features_dir: Annotated[Path, typer.Argument(metavar="FEATURES", help="`prior features` output.",
                                                 show_default=False)],
    out: OutOpt,
    changed: Annotated[Path | None, typer.Option("--changed", help="Features of the changed site.")] = None,
    bundle: Annotated[Path | None, typer.Option("--bundle", help="A bundle of the site (seeding).")] = None,
    data: Annotated[Path | None, typer.Option("--data", help="The ingested site with query runs.")] = None,
    config: ConfigOpt = "demo", set_: set_opt("prior.measure=spearman") = None,
    force: ForceOpt = False, verbose: VerboseOpt = False,
) -> None:
    with cli_errors(verbose):
        if (bundle is None) != (data is None):
            from pipeline.errors import ConfigError

            raise ConfigError("--bundle and --data go together: the seeding comparison replays the site's "
                              "query runs through the bundle's filter")
        from pipeline.prior.evaluate import run_prior_evaluate

        inputs = {"features": features_dir, **({"changed": changed} if changed else {}),
                  **({"bundle": bundle, "data": data} if bundle else {})}
        path = run_prior_evaluate(load(config, set_), inputs=inputs, outputs={"out": out}, force=force)
        typer.echo((path / "report.md").read_text().split("\n## Layer")[0])
        echo_path("report", path / "report.md")
