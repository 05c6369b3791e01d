"""`siteloc config show|check`: look at and validate presets."""

from __future__ import annotations

import typer

from stages.common import ConfigOpt, SetOpt, VerboseOpt, cli_errors, load

app = typer.Typer(help="Show or check configuration presets (configs/*.yaml).", no_args_is_help=True)


@app.command("show")
def show(config: ConfigOpt = "demo", set_: SetOpt = None, verbose: VerboseOpt = False) -> None:
    """Print the effective config (preset + overrides + defaults) as YAML."""
    import yaml

    with cli_errors(verbose):
        cfg = load(config, set_)
        typer.echo(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), nl=False)


@app.command("check")
def check(config: ConfigOpt = "demo", set_: SetOpt = None, verbose: VerboseOpt = False) -> None:
    """Validate a preset; exit 1 naming the file and key of every problem."""
    with cli_errors(verbose):
        cfg = load(config, set_)
        typer.echo(f"ok: preset '{cfg.preset}' is valid")
