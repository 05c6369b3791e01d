"""dvc.yaml stays in step with the CLI and the config: each stage calls a real command with real params."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from pipeline.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def stages():
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    for name, stage in doc["stages"].items():
        yield name, stage.get("do", stage), doc["vars"]


@pytest.mark.parametrize(("name", "stage", "dvc_vars"), list(stages()), ids=lambda v: v if isinstance(v, str) else "")
def test_stage_uses_real_command_and_params(name, stage, dvc_vars):
    from typer.main import get_command

    from stages.app import app

    command = stage["cmd"].split()
    assert command[0] == "siteloc"
    assert command[1] in get_command(app).commands, f"{name}: unknown command {command[1]}"
    values = {k: v for d in dvc_vars for k, v in d.items()}
    cfg = load_config(values["preset"]).model_dump()
    for entry in stage["params"]:
        for _file, keys in entry.items():
            for key in keys:
                node = cfg
                for part in key.split("."):
                    assert part in node, f"{name}: param {key} is not a config key"
                    node = node[part]


@pytest.mark.skipif(shutil.which("dvc") is None and not (ROOT / ".venv/bin/dvc").exists(), reason="dvc not installed")
def test_dvc_parses_the_pipeline():
    dvc = shutil.which("dvc") or str(ROOT / ".venv/bin/dvc")
    out = subprocess.run([dvc, "stage", "list"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert "ingest_log@intel-corrected" in out and "ingest_example" in out


def test_bundle_path_vars_match_the_preset():
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    values = {k: v for d in doc["vars"] for k, v in d.items()}
    cfg = load_config(values["preset"])
    assert values["site"] == cfg.synth.site and str(values["bundle_version"]) == cfg.export.version
