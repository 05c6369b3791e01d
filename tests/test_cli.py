"""The `siteloc` CLI: help explains, errors are readable (no traceback unless --verbose), imports stay light."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from stages.app import app
from tests.fixtures.capture_site import write_capture_site

runner = CliRunner()


def commands():
    import typer.main

    group = typer.main.get_command(app)
    out = []
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            out += [[name, sub] for sub in cmd.commands]
        else:
            out.append([name])
    return out


def test_top_level_help_lists_commands():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for name in ("ingest", "ingest-log", "config"):
        assert name in result.output


@pytest.mark.parametrize("argv", commands(), ids=lambda a: " ".join(a))
def test_every_command_explains_itself(argv):
    result = runner.invoke(app, [*argv, "--help"])
    assert result.exit_code == 0
    body = result.output.split("Options")[0]
    assert len(body.split()) >= 8, f"help of {' '.join(argv)} is too thin:\n{result.output}"


@pytest.mark.parametrize("argv", commands(), ids=lambda a: " ".join(a))
def test_bracketed_option_help_survives_rich_markup(argv):
    """Rich reads "[default: x]" in a help string as a style tag and drops it; escaped (\\[) it is shown."""
    import re

    import typer.main

    cmd = typer.main.get_command(app)
    for name in argv:
        cmd = cmd.commands[name]
    result = runner.invoke(app, [*argv, "--help"], env={"COLUMNS": "250"})
    shown = " ".join(result.output.split())
    for param in cmd.params:
        text = getattr(param, "help", None) or ""
        assert not re.search(r"(?<!\\)\[[a-z]", text), f"{' '.join(argv)} {param.name}: escape '[' in {text!r}"
        for inner in re.findall(r"\\\[([^\]]*)\]", text):
            assert " ".join(f"[{inner}]".split()) in shown, f"{' '.join(argv)} {param.name}: [{inner}] not shown"


def test_help_does_not_import_heavy_libraries():
    code = (
        "import sys; from stages.app import app; "
        "heavy = [m for m in ('torch', 'torchvision', 'cv2', 'pycolmap', 'sklearn', 'matplotlib', 'pyarrow') "
        "if m in sys.modules]; print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"importing the CLI pulled in {out}"


@pytest.fixture
def site(tmp_path):
    return write_capture_site(tmp_path / "site")


def test_ingest_cli_success(site, tmp_path):
    result = runner.invoke(app, ["ingest", str(site), "--out", str(tmp_path / "out"), "--config", "ci"])
    assert result.exit_code == 0, result.output
    assert "24 images in 4 stops" in result.output
    assert (tmp_path / "out" / "images.parquet").is_file()


def test_ingest_cli_bad_input_has_no_traceback(site, tmp_path):
    (site / "images" / "s0_v1.png").unlink()
    shutil.rmtree(site / "runs")
    result = runner.invoke(app, ["ingest", str(site), "--out", str(tmp_path / "out")])
    assert result.exit_code == 1
    assert "Traceback" not in result.output
    assert "captures.csv, line 3: image 'images/s0_v1.png' does not exist" in result.output
    assert not (tmp_path / "out").exists()


def test_verbose_shows_traceback(site, tmp_path):
    (site / "site.yaml").unlink()
    result = runner.invoke(app, ["ingest", str(site), "--out", str(tmp_path / "out"), "--verbose"])
    assert result.exit_code == 1
    assert "Traceback" in result.output and "site.yaml" in result.output


def test_existing_output_is_kept_without_force(site, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(app, ["ingest", str(site), "--out", str(out)]).exit_code == 0
    result = runner.invoke(app, ["ingest", str(site), "--out", str(out)])
    assert result.exit_code == 1 and "--force" in result.output
    assert runner.invoke(app, ["ingest", str(site), "--out", str(out), "--force"]).exit_code == 0


def test_bad_config_is_reported(site, tmp_path):
    result = runner.invoke(app, ["ingest", str(site), "--out", str(tmp_path / "o"), "--set", "ingest.splt=1"])
    assert result.exit_code == 1 and "ingest.splt" in result.output and "Traceback" not in result.output


def test_config_show_and_check():
    result = runner.invoke(app, ["config", "show", "--config", "paper"])
    assert result.exit_code == 0 and "preset: paper" in result.output
    assert runner.invoke(app, ["config", "check", "--config", "ci"]).exit_code == 0
    result = runner.invoke(app, ["config", "check", "--config", "nope"])
    assert result.exit_code == 1 and "unknown preset" in result.output
