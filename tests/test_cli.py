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


def commands(group=None, prefix=()):
    """The argv of every command (not group), walking subgroups to any depth."""
    import typer.main

    group = typer.main.get_command(app) if group is None else group
    out = []
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            out += commands(cmd, (*prefix, name))
        else:
            out.append([*prefix, name])
    return out


def command(argv):
    import typer.main

    cmd = typer.main.get_command(app)
    for name in argv:
        cmd = cmd.commands[name]
    return cmd


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


def _option_row(output: str, opt: str) -> str:
    """The help table row whose first option is `opt`."""
    import re

    rows = [line for line in output.splitlines() if re.match(rf"^│\s*(\*\s+)?{re.escape(opt)}\s", line)]
    assert len(rows) == 1, f"no single row for {opt} in:\n{output}"
    return rows[0]


@pytest.mark.parametrize("argv", [[], *commands()], ids=lambda a: " ".join(a) or "siteloc")
def test_flags_show_no_value_placeholder(argv):
    """An on/off flag takes no value, so its row shows no type (typer's rich help would print `<bool>`)."""
    from typer.core import TyperOption

    cmd = command(argv)
    result = runner.invoke(app, [*argv, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    flags = [p for p in cmd.params if isinstance(p, TyperOption) and p.is_flag]
    for param in [*flags, None]:
        opt = "--help" if param is None else next(o for o in param.opts if o.startswith("--"))
        help_start = "Show this" if param is None else (param.help or "").split()[0]
        row = _option_row(result.output, opt)
        assert "<" not in row.split(help_start)[0], f"{' '.join(argv)} {opt} shows a value: {row.strip()}"
    for param in cmd.params:  # options that take a value still show its type
        if isinstance(param, TyperOption) and not param.is_flag and param.opts[0] in ("--out", "--set", "--config"):
            assert "<" in _option_row(result.output, param.opts[0])


def test_localize_init_is_a_choice_list(monkeypatch, tmp_path):
    """--init lists its choices, the CLI refuses others by name, and the pipeline gets a plain string."""
    import pipeline.localize
    from pipeline.errors import ConfigError
    from stages.localize import Init

    assert tuple(Init) == pipeline.localize.INITS
    result = runner.invoke(app, ["localize", "--help"], env={"COLUMNS": "200"})
    assert "<uniform|pose|candidates|retrieval>" in result.output
    result = runner.invoke(app, ["localize", str(tmp_path), "--out", str(tmp_path / "o"), "--init", "magic"])
    assert result.exit_code == 2 and "'magic' is not one of 'uniform', 'pose', 'candidates', 'retrieval'" in \
        " ".join(result.output.replace("│", " ").split())
    seen = []

    def fake_run_localize(cfg, *, init, **kwargs):
        seen.append(init)
        raise ConfigError("stopped by the test")

    monkeypatch.setattr(pipeline.localize, "run_localize", fake_run_localize)
    for extra in (["--init", "pose"], [], ["--bundle", str(tmp_path / "b")]):
        result = runner.invoke(app, ["localize", str(tmp_path), "--out", str(tmp_path / "o"), *extra])
        assert result.exit_code == 1 and "stopped by the test" in result.output
    assert seen == ["pose", "uniform", "retrieval"] and all(type(v) is str for v in seen)


# The config section each command reads (demo and config read them all).
SECTIONS = {"ingest": "ingest", "ingest-log": "ingest_log", "train-detector": "detector",
            "evaluate-detector": "detector", "extract": "retrieval", "build-index": "retrieval",
            "query": "retrieval", "evaluate-retrieval": "retrieval", "frame-features": "sequence",
            "train-sequence": "sequence", "export": "export", "localize": "filter", "evaluate": "evaluate",
            "prior": "prior", "ingest-bag": "ingest", "export-bag": "ingest", "ingest-colmap": "ingest",
            "export-colmap": "ingest"}


@pytest.mark.parametrize("argv", [a for a in commands() if any("--set" in p.opts for p in command(a).params)],
                         ids=lambda a: " ".join(a))
def test_set_example_names_a_key_the_command_reads(argv):
    import re

    from pipeline.config import load_config, parse_overrides

    param = next(p for p in command(argv).params if "--set" in p.opts)
    example = re.search(r"e\.g\. --set (\S+)", param.help).group(1)
    result = runner.invoke(app, [*argv, "--help"], env={"COLUMNS": "250"})
    assert f"--set {example}" in result.output
    key = example.split("=", 1)[0]
    if argv == ["synth"]:  # synth's --set overrides the site preset, not the config
        from pipeline.sitegen.presets import load_site_preset

        tree = load_site_preset("tiny", parse_overrides([example])).model_dump()
    elif argv == ["synth-laser"]:  # a laser-only site preset
        from pipeline.sitegen.synth_laser import load_laser_preset

        tree = load_laser_preset("campus", parse_overrides([example])).model_dump()
    else:
        tree = load_config("demo", [example]).model_dump()
        section = SECTIONS.get(argv[0])
        assert section is None or key.split(".")[0] == section, f"{' '.join(argv)}: {key} is not in {section}"
    for part in key.split("."):
        assert isinstance(tree, dict) and part in tree, f"{' '.join(argv)}: {key} is not a key"
        tree = tree[part]


def test_help_does_not_import_heavy_libraries():
    code = (
        "import sys; from stages.app import app; "
        "heavy = [m for m in ('torch', 'torchvision', 'cv2', 'pycolmap', 'sklearn', 'matplotlib', 'pyarrow', "
        "'rosbags') if m in sys.modules]; print(','.join(heavy))"
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


def test_summary_tables_do_not_wrap_outside_a_terminal(capsys):
    """A CI log or a pipe gets each row on one line, whole, without colour codes (a terminal: rich's layout)."""
    from rich.table import Table

    from stages.common import print_tables

    cell = "a long result " * 20
    table = Table(title="summary")
    for col in ("stage", "result"):
        table.add_column(col)
    table.add_row("extract", cell.strip())
    print_tables(table, min_width=150)
    out = capsys.readouterr().out
    assert any(cell.strip() in line and "extract" in line for line in out.splitlines())
    assert "\x1b[" not in out
