"""Fixtures shared by the sitegen tests: the micro site is rendered once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.config import load_config
from pipeline.ingest import run_ingest
from tests.sitegen.micro import synth


@pytest.fixture(scope="session")
def site(tmp_path_factory) -> Path:
    """The micro site (seed 3), rendered in two processes."""
    return synth(tmp_path_factory.mktemp("synth") / "site", workers=2)


@pytest.fixture(scope="session")
def ingested(site, tmp_path_factory) -> Path:
    cfg = load_config("ci")
    return run_ingest(cfg, inputs={"site": site}, outputs={"out": tmp_path_factory.mktemp("ing") / "out"},
                      progress=False)
