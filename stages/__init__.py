"""Thin typer commands: load config, call one `pipeline.run_<stage>`, map domain errors to exit code 1."""
