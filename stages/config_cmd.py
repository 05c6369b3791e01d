"""`siteloc config show|check`: look at and validate presets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.common import ConfigOpt, SetOpt, VerboseOpt, cli_errors, load

app = typer.Typer(help="Show or check configuration presets (configs/*.yaml).", no_args_is_help=True)


@app.command("show")
def show(
    config: ConfigOpt = "demo",
    set_: SetOpt = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Write it to this file (atomically) instead of printing it, with a header "
                     "saying how it was made: `--out configs/params.yaml` sets the config `dvc repro` runs."),
    ] = None,
    explain: Annotated[
        str | None,
        typer.Option("--explain", "-e", metavar="KEY", help="Explain one key (e.g. filter.camera.threshold) or "
                     "section: its type, default, value in this config, what it does and which stage reads it."),
    ] = None,
    verbose: VerboseOpt = False,
) -> None:
    """Print the effective config (preset + overrides + defaults) as YAML, or write it with --out."""
    import yaml

    with cli_errors(verbose):
        from pipeline.config import resolved_params_text
        from pipeline.io.atomic import write_text_atomic

        cfg = load(config, set_)
        if explain is not None:
            from pipeline.config.keys import explain as explain_key

            typer.echo(explain_key(explain, cfg))
            return
        if out is None:
            typer.echo(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), nl=False)
            return
        write_text_atomic(out, resolved_params_text(cfg))
        typer.echo(f"wrote {out}: preset '{cfg.preset}' with every default")


@app.command("check")
def check(config: ConfigOpt = "demo", set_: SetOpt = None, verbose: VerboseOpt = False) -> None:
    """Validate a preset; exit 1 naming the file and key of every problem."""
    with cli_errors(verbose):
        cfg = load(config, set_)
        typer.echo(f"ok: preset '{cfg.preset}' is valid")


@app.command("docs")
def docs(
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write it here (atomically) instead of printing "
                                             "it: docs/configuration.md.")] = None,
    verbose: VerboseOpt = False,
) -> None:
    """Every config key with its type, default and description, as Markdown (docs/configuration.md)."""
    with cli_errors(verbose):
        from pipeline.config.keys import markdown
        from pipeline.io.atomic import write_text_atomic

        text = markdown()
        if out is None:
            typer.echo(text, nl=False)
            return
        write_text_atomic(out, text)
        typer.echo(f"wrote {out}")
