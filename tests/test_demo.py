"""The DVC pipeline end to end on the ci preset, in a temporary copy of the project.

`siteloc demo` reproduces every stage through DVC; afterwards dvc.lock matches the outputs (`dvc status`
is clean and `dvc repro` runs nothing); a change of one parameter reruns exactly the stages that read it
and those downstream; `dvc metrics diff` and `dvc plots diff` compare the two runs; a missing log is
skipped with a warning while everything else is reused. One test: each run of the chain costs minutes.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.fixtures.carmen_logs import room_log_lines, write_log

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
LOGS = ("intel-corrected", "aces-corrected", "csail-corrected", "freiburg-079-corrected", "fhw-corrected")


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "COLUMNS": "200"}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)


def _copy_project(dest: Path) -> None:
    """The working tree as git sees it (tracked and untracked, not ignored), committed in a new repository."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True,
                           check=True).stdout.decode().split("\0")
    for rel in filter(None, files):
        if (ROOT / rel).is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, dest / rel)
    (dest / "dvc.lock").unlink(missing_ok=True)
    _git(dest, "init", "-q")
    _commit(dest, "copy")


def _git(cwd: Path, *args: str) -> None:
    subprocess.run(["git", "-c", "user.email=ci@siteloc", "-c", "user.name=ci", *args], cwd=cwd, check=True,
                   capture_output=True)


def _commit(cwd: Path, message: str) -> None:
    _git(cwd, "add", "-A")
    _git(cwd, "commit", "-q", "-m", message)


def _ran(output: str) -> set[str]:
    return {line.split("'")[1] for line in output.splitlines() if line.startswith("Running stage '")}


@pytest.mark.slow
@pytest.mark.skipif(not (BIN / "dvc").exists(), reason="dvc not installed")
def test_the_dvc_pipeline_runs_is_recorded_and_reruns_only_what_changed(tmp_path):
    project = tmp_path / "main"
    carmen = tmp_path / "shared" / "data" / "carmen"  # dvc.yaml's carmen_dir, relative to the project
    carmen.mkdir(parents=True)
    for name in LOGS:
        write_log(carmen / f"{name}.log.gz", room_log_lines(20))
    _copy_project(project)

    assert _run([str(BIN / "dvc"), "dag"], project).returncode == 0
    first = _run(["siteloc", "demo", "--config", "ci"], project)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    summary = json.loads((project / "data" / "demo-summary.json").read_text())
    stages = set(summary) - {"total"}
    assert len(stages) == 33 and not any(summary[s]["reused"] for s in stages)
    assert summary["ingest_bag"]["report"]["stops"] == summary["synth"]["report"]["stops"]  # the bag round trip
    assert summary["ingest_log@intel-corrected"]["report"]["scans"] == 20
    assert summary["synth"]["report"]["capture_images"] == 6 * summary["synth"]["report"]["stops"]
    bundle = project / "bundles" / "tiny-0.1.0"
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert (project / "bundles" / "tiny-0.1.0.tar.gz").is_file() and (bundle / "models" / "sequence.onnx").is_file()
    provenance = manifest["provenance"]
    assert provenance["built_by"] == "dvc repro (stage export)"
    assert provenance["inputs"]["model"]["dvc_md5"].endswith(".dir")  # the lock's entry for models/detector
    report = json.loads((project / "reports" / "tiny" / "metrics.json").read_text())
    assert report["summary"]["proposed"]["replays"] == len(report["runs"]) * report["trials"]
    # The update chain: only the re-captured area's images are described again; v2 names v1 as its parent.
    reuse = summary["extract_update"]["report"]
    assert 0 < reuse["computed_images"] < reuse["images"] and reuse["reuse"]["describer_matches"]
    v2 = json.loads((project / "bundles" / "update" / "tiny-0.1.1" / "manifest.json").read_text())
    assert v2["parent"]["name"] == "tiny-0.1.0" and v2["changelog"]["areas_changed"]
    assert all(a.startswith("corridor_h1") for a in v2["changelog"]["areas_changed"])
    assert (project / "reports" / "tiny-check" / "drift.png").is_file()
    # The area prior follows: the re-captured images replace their old rows, the rest are reused.
    feats = summary["prior_features_update"]["report"]
    assert 0 < feats["reuse"]["reused_images"] < feats["images"]
    u = summary["prior_update"]["report"]["updated"][-1]
    assert u["added"] > 0 and u["dropped"] > 0 and u["kept"] > u["added"]
    assert v2["changelog"]["components"]["prior"] == "changed"
    # So does the sequence database: frames encoded only where they changed, described by the LSTM in use.
    frames = summary["frame_features_update"]["report"]
    assert 0 < frames["reuse"]["reused_frames"] and frames["computed_frames"] < frames["frames"]
    assert summary["sequence_update"]["report"]["epochs"] == 0
    assert v2["changelog"]["components"]["sequence"] == "changed"

    # dvc.lock matches the outputs: nothing is stale and a second run does nothing.
    status = _run([str(BIN / "dvc"), "status"], project)
    assert "Data and pipelines are up to date" in status.stdout, status.stdout
    again = _run([str(BIN / "dvc"), "repro"], project)
    assert again.returncode == 0 and not _ran(again.stdout), again.stdout[-2000:]
    _commit(project, "first run")

    # One parameter: exactly the stages that read the `evaluate` section, and nothing upstream.
    changed = _run(["siteloc", "demo", "--set", "evaluate.converge_hold=5"], project)
    assert changed.returncode == 0, changed.stderr[-3000:]
    redone = {name for name, s in json.loads((project / "data" / "demo-summary.json").read_text()).items()
              if name != "total" and not s["reused"]}
    assert redone == {"evaluate", "prior_evaluate"}
    assert _run([str(BIN / "dvc"), "status"], project).stdout.strip() == "Data and pipelines are up to date."
    diff = _run([str(BIN / "dvc"), "params", "diff", "--md"], project).stdout
    assert "evaluate.converge_hold" in diff and "10" in diff and "5" in diff
    metrics = _run([str(BIN / "dvc"), "metrics", "diff", "--all", "--json", "HEAD"], project)
    assert metrics.returncode == 0 and "reports/tiny/headline.json" in json.loads(metrics.stdout)
    plots = _run([str(BIN / "dvc"), "plots", "diff", "HEAD", "--json"], project)
    data = json.loads(plots.stdout)["data"]
    assert {"detector loss", "retrieval recall@N", "localization error CDF", "kidnapping recovery steps"} <= set(data)
    revisions = {row["rev"] for spec in data["localization error CDF"]
                 for row in spec["content"]["data"]["values"]}
    assert revisions == {"HEAD", "workspace"}

    # A log that is not there: its stage is skipped with a warning, everything else is reused.
    (carmen / "fhw-corrected.log.gz").unlink()
    third = _run(["siteloc", "demo"], project)
    assert third.returncode == 0 and "ingest_log@fhw-corrected skipped" in third.stderr
    summary = json.loads((project / "data" / "demo-summary.json").read_text())
    assert "ingest_log@fhw-corrected" not in summary
    assert all(s["reused"] for name, s in summary.items() if name != "total")
