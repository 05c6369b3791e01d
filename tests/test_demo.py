"""`siteloc demo`: runs the chain on a folder of logs and the example site, resumes, and redoes with --force."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from stages.app import app
from tests.fixtures.carmen_logs import room_log_lines, write_log

runner = CliRunner()


def test_demo_runs_resumes_and_forces(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    write_log(logs / "room-corrected.log.gz", room_log_lines(20))
    data = tmp_path / "data"
    args = ["demo", "--data", str(data), "--carmen-dir", str(logs), "--config", "ci", "--models",
            str(tmp_path / "models"), "--bundles", str(tmp_path / "bundles"), "--reports", str(tmp_path / "reports")]

    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    assert (data / "carmen" / "room-corrected" / "map.yaml").is_file()
    assert (data / "example" / "ingested" / "images.parquet").is_file()
    assert (data / "reference" / "ingested" / "boxes.parquet").is_file()
    summary = json.loads((data / "demo-summary.json").read_text())
    assert summary["ingest-log room-corrected"]["report"]["scans"] == 20
    synth = summary["synth tiny"]["report"]
    assert synth["capture_images"] == 6 * synth["stops"]
    assert summary["ingest tiny"]["report"]["images"] == synth["capture_images"]
    assert "synth tiny" in first.output.replace("│", " ") or "tiny" in first.output
    total = summary.pop("total")["seconds"]
    assert not any(step["reused"] for step in summary.values())
    assert total == pytest.approx(sum(step["seconds"] for step in summary.values()), abs=0.1 * len(summary))
    assert "total:" in first.output
    # the main job end to end: retrieval database, bundle, and the query runs localized from the bundle alone
    assert {"extract", "build-index", "evaluate-retrieval", "export", "evaluate (bundle)"} <= set(summary)
    bundle = next((tmp_path / "bundles").glob("*-0.1.0"))
    assert (bundle / "manifest.json").is_file() and (bundle.parent / f"{bundle.name}.tar.gz").is_file()
    report = json.loads((tmp_path / "reports" / bundle.name.removesuffix("-0.1.0") / "metrics.json").read_text())
    assert report["runs"] and report["summary"]["proposed"]["replays"] == len(report["runs"]) * report["trials"]
    # ... with the image-sequence LSTM trained on the mapping runs and shipped in the bundle
    assert {"frame-features", "train-sequence"} <= set(summary)
    assert (bundle / "models" / "sequence.onnx").is_file() and "sequence" in report["summary"]
    assert report["filter"]["relocalise_with"] == "both"

    map_pgm = data / "carmen" / "room-corrected" / "map.pgm"
    mtime = map_pgm.stat().st_mtime_ns
    second = runner.invoke(app, args)
    assert second.exit_code == 0 and "reused" in second.output
    assert map_pgm.stat().st_mtime_ns == mtime
    assert all(step["reused"] for name, step in json.loads((data / "demo-summary.json").read_text()).items()
               if name != "total")

    forced = runner.invoke(app, [*args, "--force"])
    assert forced.exit_code == 0
    assert not any(step["reused"] for name, step in json.loads((data / "demo-summary.json").read_text()).items()
                   if name != "total")


def test_demo_without_logs_warns_and_does_not_reuse_a_site_made_from_other_settings(tmp_path):
    """No logs: a warning, and the example site is still ingested. Run again with another synth seed,
    the site and everything made from it are redone, not reused (one test: each demo costs a minute)."""
    data = tmp_path / "d"
    args = ["demo", "--data", str(data), "--carmen-dir", str(tmp_path / "none"), "--config", "ci", "--models",
            str(tmp_path / "m"), "--bundles", str(tmp_path / "b"), "--reports", str(tmp_path / "r")]
    result = runner.invoke(app, args)  # never the repository's own folders
    assert result.exit_code == 0, result.output
    assert "no CARMEN logs" in result.output
    assert (data / "example" / "ingested" / "report.json").is_file()
    assert json.loads((data / "demo-summary.json").read_text())["synth tiny"]["report"]["seed"] != 4
    again = runner.invoke(app, [*args, "--set", "synth.seed=4"])
    assert again.exit_code == 0, again.output
    summary = json.loads((data / "demo-summary.json").read_text())
    assert not summary["synth tiny"]["reused"] and not summary["ingest tiny"]["reused"]
    assert summary["synth tiny"]["report"]["seed"] == 4
    redone = {name for name, step in summary.items() if name != "total" and not step["reused"]}
    assert redone == set(summary) - {"total", "ingest example-site"}  # the example site reads nothing of it
