"""The `siteloc` command line. Heavy libraries are imported inside commands so `--help` stays fast."""

from __future__ import annotations

import typer

from stages import (
    bag,
    check,
    colmap,
    config_cmd,
    demo,
    diff,
    evaluate,
    evaluate_detector,
    export,
    ingest,
    ingest_log,
    localize,
    places,
    prior,
    retrieval,
    sequence,
    synth,
    synth_laser,
    train_detector,
    update,
)
from stages.common import Group, help_text

app = typer.Typer(
    name="siteloc",
    cls=Group,
    help=(
        "Indoor localization from a camera and a 2D laser.\n\n"
        "Offline steps turn a mapping team's captures and laser logs into a site database; the runtime filter "
        "localizes a robot against it. Each step reads a config preset (--config) and writes "
        "its effective config beside its outputs. Errors are reported without tracebacks; add --verbose to see them."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

app.command("ingest", help=help_text(ingest.HELP))(ingest.ingest)
app.command("ingest-bag", help=help_text(bag.INGEST_HELP))(bag.ingest_bag)
app.command("export-bag", help=help_text(bag.EXPORT_HELP))(bag.export_bag)
app.command("ingest-colmap", help=help_text(colmap.INGEST_HELP))(colmap.ingest_colmap)
app.command("export-colmap", help=help_text(colmap.EXPORT_HELP))(colmap.export_colmap)
app.command("ingest-log", help=help_text(ingest_log.HELP))(ingest_log.ingest_log)
app.command("synth", help=help_text(synth.HELP))(synth.synth)
app.command("synth-laser", help=help_text(synth_laser.HELP))(synth_laser.synth_laser)
app.command("train-detector", help=help_text(train_detector.HELP))(train_detector.train_detector)
app.command("evaluate-detector", help=help_text(evaluate_detector.HELP))(evaluate_detector.evaluate_detector)
app.command("train-place", help=help_text(retrieval.TRAIN_PLACE_HELP))(retrieval.train_place)
app.command("extract", help=help_text(retrieval.EXTRACT_HELP))(retrieval.extract)
app.command("build-index", help=help_text(retrieval.INDEX_HELP))(retrieval.build_index)
app.command("query", help=help_text(retrieval.QUERY_HELP))(retrieval.query)
app.command("evaluate-retrieval", help=help_text(retrieval.EVALUATE_HELP))(retrieval.evaluate_retrieval)
app.command("evaluate-places", help=help_text(places.HELP))(places.evaluate_places)
app.command("frame-features", help=help_text(sequence.FRAMES_HELP))(sequence.frame_features)
app.command("train-sequence", help=help_text(sequence.TRAIN_HELP))(sequence.train_sequence)
app.command("export", help=help_text(export.HELP))(export.export)
app.command("update", help=help_text(update.HELP))(update.update)
app.command("check", help=help_text(check.HELP))(check.check)
app.command("diff", help=help_text(diff.HELP))(diff.diff)
app.command("localize", help=help_text(localize.HELP))(localize.localize)
app.command("evaluate", help=help_text(evaluate.HELP))(evaluate.evaluate)
app.command("demo", help=help_text(demo.HELP))(demo.demo)
app.add_typer(prior.app, name="prior", help=help_text(prior.APP_HELP))
app.add_typer(config_cmd.app, name="config")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
