"""dvc.yaml is a pipeline DVC accepts, in step with the CLI, the config and the code each stage runs.

The chain itself (`dvc repro` on the ci preset, a rerun that does nothing, one parameter that reruns
exactly its downstream stages) runs in tests/test_demo.py.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.code_deps import code_of, command_callback, covered, stage_command_words
from pipeline.config import load_config, resolved_params_text

ROOT = Path(__file__).resolve().parents[1]
DOC = yaml.safe_load((ROOT / "dvc.yaml").read_text())
PARAMS = yaml.safe_load((ROOT / "configs" / "params.yaml").read_text())
DVC = shutil.which("dvc") or str(Path(sys.executable).parent / "dvc")


def stages():
    for name, stage in DOC["stages"].items():
        yield name, stage.get("do", stage)


STAGES = list(stages())
IDS = [name for name, _ in STAGES]


def _lookup(tree: dict, dotted: str):
    node = tree
    for part in dotted.split("."):
        assert isinstance(node, dict) and part in node, f"{dotted} is not a key of configs/params.yaml"
        node = node[part]
    return node


def test_the_params_file_is_the_demo_preset_with_every_default():
    """configs/params.yaml is what `siteloc config show --config demo --out configs/params.yaml` writes."""
    expected = resolved_params_text(load_config("demo"))
    assert (ROOT / "configs" / "params.yaml").read_text() == expected, (
        "configs/params.yaml is stale: run `siteloc config show --config demo --out configs/params.yaml`")
    assert load_config(ROOT / "configs" / "params.yaml") == load_config("demo")


@pytest.mark.parametrize(("name", "stage"), STAGES, ids=IDS)
def test_stage_runs_a_real_command_on_the_params_file(name, stage):
    words = stage_command_words(stage["cmd"])
    command_callback(words)  # raises for a command the CLI does not have
    assert "--config ${params}" in stage["cmd"], f"{name}: every stage reads configs/params.yaml"
    (entry,) = stage["params"]
    ((file, keys),) = entry.items()
    assert file == "${params}" and keys, name
    for key in keys:
        _lookup(PARAMS, key)


@pytest.mark.parametrize(("name", "stage"), STAGES, ids=IDS)
def test_stage_deps_cover_the_code_it_runs(name, stage):
    """Every project file the command may import is a dependency, so a code change reruns the stage."""
    files = code_of(command_callback(stage_command_words(stage["cmd"])))
    missing = sorted(p.relative_to(ROOT).as_posix() for p in files if not covered(p, stage["deps"]))
    assert not missing, f"{name}: add to its deps in dvc.yaml: {missing} (python -m pipeline.code_deps)"


def test_code_deps_follow_lazy_and_relative_imports(tmp_path):
    """The import walk sees imports inside functions (commands import lazily) and __init__ files with code."""
    files = {p.relative_to(ROOT).as_posix() for p in code_of(command_callback(["train-detector"]))}
    assert {"stages/train_detector.py", "pipeline/detection/train.py", "pipeline/__init__.py",
            "pipeline/config/__init__.py", "pipeline/config/detector.py", "stages/common.py"} <= files
    assert "stages/retrieval.py" not in files and "pipeline/sitegen/render.py" not in files


def test_metrics_and_plots_are_files_inside_stage_outputs():
    """DVC refuses outputs that overlap; metrics and plots are named at the top level, inside the outputs."""
    site, version = PARAMS["synth"]["site"], PARAMS["export"]["version"]

    def resolve(path: str) -> str:
        return path.replace("${synth.site}", site).replace("${export.version}", version)

    outs = [resolve(o) for _, s in STAGES for o in s.get("outs", [])]
    assert not any(k in s for _, s in STAGES for k in ("metrics", "plots")), "use the top-level sections"
    paths = list(DOC["metrics"])
    for plot in DOC["plots"]:
        ((_, spec),) = plot.items()
        paths += list(spec["y"])
    for path in map(resolve, paths):
        assert any(path.startswith(o + "/") for o in outs), f"{path} is in no stage's output"


@pytest.mark.skipif(not Path(DVC).exists(), reason="dvc not installed")
def test_dvc_builds_the_graph():
    """`dvc dag` builds the whole graph: it refuses overlapping outputs, cycles and bad interpolation."""
    out = subprocess.run([DVC, "dag", "--md"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "export" in out.stdout and "evaluate" in out.stdout and "ingest_log@intel-corrected" in out.stdout
    listed = subprocess.run([DVC, "stage", "list", "--name-only"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.split()
    assert "train_sequence" in listed and len(listed) == len(STAGES) + 4  # foreach: five logs


def test_bundle_path_matches_what_export_writes():
    """export writes bundles/<site>-<version>, the site's name being synth.site for the reference site."""
    cfg = load_config(ROOT / "configs" / "params.yaml")
    (export,) = [s for n, s in STAGES if n == "export"]
    assert f"bundles/{cfg.synth.site}-{cfg.export.version}" in [
        o.replace("${synth.site}", cfg.synth.site).replace("${export.version}", cfg.export.version)
        for o in export["outs"]]


def test_no_project_modules_import_each_other(tmp_path, monkeypatch):
    """Import cycles are design debts (issue 29): none among pipeline/ and stages/, lazy imports included.
    The walk itself finds one planted in a copy of the tree."""
    import shutil

    from pipeline import code_deps

    assert code_deps.import_cycles() == []
    for package in ("pipeline", "stages"):
        shutil.copytree(ROOT / package, tmp_path / package)
    (tmp_path / "pipeline" / "io" / "tables.py").write_text(
        (tmp_path / "pipeline" / "io" / "tables.py").read_text() + "\n\ndef _cycle():\n"
        "    from pipeline.retrieval.extract import run_extract  # noqa: F401\n")
    monkeypatch.setattr(code_deps, "ROOT", tmp_path)
    cycles = code_deps.import_cycles()
    assert any({"pipeline/io/tables.py", "pipeline/retrieval/extract.py"} <= set(group) for group in cycles)
