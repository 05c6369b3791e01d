"""What every command shares: config options, error handling, the console."""

from __future__ import annotations

import contextlib
import sys
import traceback
from collections.abc import Iterator
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from typer.core import TyperGroup, TyperOption

ConfigOpt = Annotated[
    str,
    typer.Option(
        "--config",
        "-c",
        help="Preset name in configs/ (demo, ci, paper) or a path to a YAML file.",
        rich_help_panel="Configuration",
    ),
]


def set_opt(example: str) -> Any:
    """The --set option; `example` (KEY=VALUE) should name a key of the config section the command reads."""
    return Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            "-s",
            help=f"Override one config key, e.g. --set {example} (repeatable).",
            rich_help_panel="Configuration",
        ),
    ]


SetOpt = set_opt("ingest.split.seed=3")
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Output directory.", show_default=False)]
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="Show full tracebacks on errors.")]
ForceOpt = Annotated[bool, typer.Option("--force", "-f", help="Replace an existing output (atomically).")]


class Executor(StrEnum):
    LOCAL = "local"
    RAY = "ray"


EngineOpt = Annotated[Executor, typer.Option(
    "--engine",
    help="local: this machine's own pool of workers; ray: Ray actors, on this machine or on the cluster at "
         "--ray-address (needs the ray extra: pip install siteloc\\[ray]); the same output either way.")]
RayAddressOpt = Annotated[str | None, typer.Option(
    "--ray-address", show_default=False,
    help="With --engine ray: a running cluster (host:6379, or auto); without it a local Ray is started.")]


def print_tables(*tables, min_width: int = 0) -> None:
    """Rich tables on stdout. In a terminal at least `min_width` wide; elsewhere (a CI log, a pipe, a file) as
    wide as their content, so no cell wraps into lines of its neighbours, and without colour codes."""
    from rich.console import Console

    console = (Console(width=max(Console().width, min_width)) if sys.stdout.isatty()
               else Console(width=1000, no_color=True, force_terminal=False))
    for table in tables:
        console.print(table)


def engine_args(engine: Executor, ray_address: str | None) -> dict:
    """run_<stage>'s executor keywords; --ray-address without --engine ray is a ConfigError."""
    if ray_address is not None and engine != Executor.RAY:
        from pipeline.errors import ConfigError

        raise ConfigError("--ray-address goes with --engine ray")
    return {"executor": str(engine), "ray_address": ray_address}


def _plain_flags(command, ctx) -> None:
    """Give the on/off flags of `command` and its subcommands (--help too) an empty metavar.

    Typer's rich help prints every option's type after it, `<bool>` for a flag, as if it took a value.
    """
    for param in command.get_params(ctx):
        if isinstance(param, TyperOption) and param.is_flag and param.metavar is None:
            param.metavar = ""
    for name, sub in getattr(command, "commands", {}).items():
        _plain_flags(sub, sub.context_class(sub, parent=ctx, info_name=name, **sub.context_settings))


class Group(TyperGroup):
    """The root command group: every command's help shows its flags without a value placeholder."""

    def get_params(self, ctx):
        if not getattr(self, "_flags_plain", False):
            self._flags_plain = True
            _plain_flags(self, ctx)
        return super().get_params(ctx)


def err(message: str) -> None:
    typer.secho(printable(message), fg=typer.colors.RED, err=True)


def printable(message: str, line_limit: int = 1000) -> str:
    """`message` safe for a terminal: control bytes (an escape sequence read from a file) shown escaped, and
    each line cut at `line_limit` characters. Messages quote input through `excerpt`; this is the backstop."""
    from pipeline.errors import excerpt

    return "\n".join(excerpt(line, line_limit) if len(line) > line_limit or not line.isprintable() else line
                     for line in message.split("\n"))


@contextlib.contextmanager
def cli_errors(verbose: bool) -> Iterator[None]:
    """Turn domain errors into a message and exit code 1; tracebacks only with --verbose."""
    from pipeline.errors import SitelocError

    try:
        yield
    except typer.Exit:
        raise
    except SitelocError as exc:
        if verbose:
            traceback.print_exc()
        err(f"error: {exc}")
        raise typer.Exit(1) from None
    except KeyboardInterrupt:
        err("interrupted: no partial output was kept; rerun the command to resume")
        raise typer.Exit(130) from None
    except Exception as exc:  # an unexpected failure is still reported readably
        if verbose:
            traceback.print_exc()
        else:
            err(f"error: unexpected {type(exc).__name__}: {exc}\n(rerun with --verbose for the traceback)")
        raise typer.Exit(1) from None


def load(config: str, overrides: list[str] | None):
    from pipeline.config import load_config

    return load_config(config, overrides or [])


def echo_path(label: str, path: Path) -> None:
    typer.echo(f"{label}: {path}", file=sys.stdout)


def help_text(text: str) -> str:
    """Join wrapped lines into paragraphs (the terminal re-wraps them); keep indented lines as they are."""
    out: list[str] = []
    for block in text.strip().split("\n\n"):
        lines = block.split("\n")
        if any(line.startswith("  ") for line in lines):
            out.append("\n".join(lines))
        else:
            out.append(" ".join(line.strip() for line in lines))
    return "\n\n".join(out)
