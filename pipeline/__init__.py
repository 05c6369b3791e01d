"""siteloc: camera + 2D-laser indoor localization.

`pipeline` is the library (pure, typed stage functions `run_<stage>(cfg, *, inputs, outputs) -> Path`);
`stages` holds the thin typer CLI that wraps them.
"""

__version__ = "0.1.0"
