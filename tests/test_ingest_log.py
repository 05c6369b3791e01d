"""`siteloc ingest-log` end to end: outputs, determinism, readable errors, and the real intel log."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from pipeline.config import load_config
from pipeline.ingest_log import run_ingest_log, run_name
from pipeline.io.map_yaml import read_map
from pipeline.io.tables import read_table, table_metadata
from stages.app import app
from tests.fixtures.carmen_logs import ROOM, room_log_lines, room_poses, write_log

runner = CliRunner()
OUTPUTS = [
    "config.yaml",
    "map.pgm",
    "map.yaml",
    "preview.png",
    "report.json",
    "report.md",
    "runs/room.parquet",
]


@pytest.fixture
def room_log(tmp_path):
    return write_log(tmp_path / "room.log.gz", room_log_lines(n_scans=30, n_beams=181, no_return_every=20))


def _invoke(*args: str):
    return runner.invoke(app, ["ingest-log", *args, "--config", "ci"])


def test_run_names():
    assert run_name("a/intel-corrected.log.gz") == "intel-corrected"
    assert run_name("fhw.log") == "fhw" and run_name("x.gz") == "x" and run_name("odd") == "odd"


def test_cli_writes_every_output(tmp_path, room_log):
    out = tmp_path / "out"
    result = _invoke(str(room_log), "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "30 scans x 181 beams" in result.output and str(out) in result.output
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == OUTPUTS

    table = read_table(out / "runs" / "room.parquet", "runs")
    meta = table_metadata(table)
    assert meta["odometry"] == "synthesised" and meta["source"] == "room.log.gz" and meta["time_source"] == "log"
    assert json.loads(meta["odometry_noise"]) == load_config("ci").ingest_log.odometry_noise.model_dump()
    assert meta["odometry_seed"] == "0"
    cols = table.to_pydict()
    assert cols["step"] == list(range(30)) and set(cols["run"]) == {"room"}
    np.testing.assert_allclose(np.stack([cols["gt_x"], cols["gt_y"], cols["gt_theta"]], 1), room_poses(30), atol=1e-6)
    assert cols["odom_x"][0] == cols["odom_y"][0] == cols["odom_theta"][0] == 0.0
    ranges = np.array(cols["ranges"], dtype=np.float32)
    assert ranges.shape == (30, 181) and (ranges[:, ::20] == np.float32(40.0)).all()
    assert cols["angle_min"][0] == pytest.approx(-np.pi / 2) and cols["range_max"][0] == 40.0

    occ = read_map(out / "map.yaml")
    assert occ.resolution == pytest.approx(0.1)  # the ci preset
    x0, y0, x1, y1 = ROOM
    assert occ.origin_x <= x0 - 1.0 and occ.origin_x + occ.width * occ.resolution >= x1 + 1.0

    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == 30 and report["beams"] == 181 and report["skipped_lines"] == 0
    assert report["map_size_cells"] == [occ.width, occ.height]
    assert report["endpoint_on_occupied_share_tol1"] > 0.99
    assert report["message_counts"] == {"#": 1, "FLASER": 30, "ODOM": 30, "PARAM": 1}
    path = np.hypot(*np.diff(room_poses(30)[:, :2], axis=0).T).sum()
    assert report["path_length_m"] == pytest.approx(path, abs=0.01)
    assert "| scans x beams | 30 x 181 |" in (out / "report.md").read_text()
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["stage"] == "ingest-log" and config["inputs"] == {"log": str(room_log)}


def test_every_m_keeps_one_scan_per_metre_and_maps_from_all(tmp_path, room_log):
    from pipeline.ingest_log import every_metre

    poses = room_poses(30)
    keep = every_metre(poses, 1.0)
    # Brute-force twin: walk the path, keep a scan once 1 m has been travelled since the last kept one.
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    twin, last = [0], 0.0
    for i, d in enumerate(travelled):
        if d - last >= 1.0:
            twin.append(i)
            last = d
    assert keep.tolist() == twin and 1 < len(twin) < 30
    assert every_metre(poses, 0.0).tolist() == list(range(30))

    full, sparse = tmp_path / "full", tmp_path / "sparse"
    assert _invoke(str(room_log), "--out", str(full)).exit_code == 0
    res = _invoke(str(room_log), "--out", str(sparse), "--every-m", "1")
    assert res.exit_code == 0, res.output
    cols = read_table(sparse / "runs" / "room.parquet", "runs").to_pydict()
    np.testing.assert_allclose(np.column_stack([cols["gt_x"], cols["gt_y"]]), poses[twin, :2], atol=1e-6)
    assert cols["step"] == list(range(len(twin)))
    assert (sparse / "map.pgm").read_bytes() == (full / "map.pgm").read_bytes()  # the map: every scan
    report = json.loads((sparse / "report.json").read_text())
    assert report["scans"] == len(twin) and report["scans_in_log"] == 30 and report["scan_every_m"] == 1.0


def test_outputs_are_deterministic(tmp_path, room_log):
    cfg = load_config("ci")
    a = run_ingest_log(cfg, inputs={"log": room_log}, outputs={"out": tmp_path / "a"}, progress=False)
    b = run_ingest_log(cfg, inputs={"log": room_log}, outputs={"out": tmp_path / "b"}, progress=False)
    for name in OUTPUTS:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_malformed_line_fails_cleanly_and_skip_bad_lines_counts_it(tmp_path):
    lines = room_log_lines(n_scans=10, n_beams=181)
    lines[7] = lines[7].rsplit(" ", 4)[0]  # drop 4 fields of a FLASER line (file line 8)
    assert lines[7].startswith("FLASER")
    log = write_log(tmp_path / "room.log", lines)
    out = tmp_path / "out"

    result = _invoke(str(log), "--out", str(out))
    assert result.exit_code == 1
    assert "line 8" in result.output and "need 192 fields" in result.output and "found 188" in result.output
    assert "--skip-bad-lines" in result.output and "Traceback" not in result.output
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*"))

    result = _invoke(str(log), "--out", str(out), "--skip-bad-lines")
    assert result.exit_code == 0, result.output
    assert "skipped 1 malformed line" in result.output
    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == 9 and report["skipped_lines"] == 1
    assert report["skipped_line_problems"][0].startswith("line 8: FLASER")


def test_existing_output_needs_force(tmp_path, room_log):
    out = tmp_path / "out"
    assert _invoke(str(room_log), "--out", str(out)).exit_code == 0
    (out / "marker").write_text("old")
    result = _invoke(str(room_log), "--out", str(out))
    assert result.exit_code == 1 and "--force" in result.output and "Traceback" not in result.output
    assert (out / "marker").exists()
    assert _invoke(str(room_log), "--out", str(out), "--force").exit_code == 0
    assert not (out / "marker").exists()


def test_missing_and_empty_logs(tmp_path):
    result = _invoke(str(tmp_path / "nope.log.gz"), "--out", str(tmp_path / "out"))
    assert result.exit_code == 1 and "nope.log.gz" in result.output and "not found" in result.output
    empty = write_log(tmp_path / "empty.log", ["# no laser here", "ODOM 0 0 0 0 0 0 1 h 1"])
    result = _invoke(str(empty), "--out", str(tmp_path / "out"))
    assert result.exit_code == 1 and "no laser scans" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.realdata
@pytest.mark.slow
def test_intel_map_explains_its_scans(tmp_path):
    from tests.fixtures.carmen_logs import require_carmen_dir

    log = require_carmen_dir() / "intel-corrected.log.gz"
    cfg = load_config("demo")  # 0.05 m cells
    out = run_ingest_log(cfg, inputs={"log": log}, outputs={"out": tmp_path / "intel"}, progress=False)
    report = json.loads((out / "report.json").read_text())
    assert (report["scans"], report["beams"], report["time_source"]) == (910, 180, "step_index")
    assert report["path_length_m"] == pytest.approx(500, abs=5)  # README: 500 m
    # Measured at 0.05 m: 0.769 of the endpoints on an occupied cell, 0.960 within one cell. The exact
    # share is lowered by beams grazing walls (they clear wall cells) and by clutter and people seen
    # once; the bounds sit ~0.05 / 0.03 under the measurement, so a regression (wrong beam angles, a
    # flipped axis, a pose-frame mix-up) fails, whereas such errors give shares far below 0.5.
    assert report["endpoint_on_occupied_share_tol0"] >= 0.72
    assert report["endpoint_on_occupied_share_tol1"] >= 0.93
    occ = read_map(out / "map.yaml")
    assert 0.01 < occ.occupied.mean() < 0.05 and occ.free.mean() > 0.25


def _flaser_fields(line: str, **fields) -> str:
    """A FLASER line with ranges (`ranges=`) or the pose x (`x=`) replaced."""
    tokens = line.split()
    n = int(tokens[1])
    if "ranges" in fields:
        tokens[2 : 2 + n] = [fields["ranges"]] * n
    if "x" in fields:
        tokens[2 + n] = fields["x"]
    return " ".join(tokens)


@pytest.mark.parametrize(("value", "words"), [("nan", "no valid ranges found, 0 of 1810"),
                                               ("81.83", "no valid ranges found, 0 of 1810"),
                                               ("0", "no valid ranges found, 0 of 1810")])
def test_a_log_without_valid_ranges_is_refused(tmp_path, value, words):
    """An all-NaN (or all no-return) log used to exit 0 with an all-unknown map."""
    lines = [_flaser_fields(ln, ranges=value) if ln.startswith("FLASER") else ln
             for ln in room_log_lines(n_scans=10, n_beams=181)]
    log, out = write_log(tmp_path / "nan.log", lines), tmp_path / "out"
    before = log.read_bytes()
    result = _invoke(str(log), "--out", str(out))
    assert result.exit_code == 1 and "Traceback" not in result.output and "unexpected" not in result.output
    assert str(log) in result.output and words in result.output and "at least 1%" in result.output
    assert "max_range_m" in result.output
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*")) and log.read_bytes() == before


def test_the_valid_range_floor_is_one_percent(tmp_path):
    """10 valid readings of 1810 (0.55 %) are refused as too few; one whole valid scan of ten (10 %) maps."""
    lines = room_log_lines(n_scans=10, n_beams=181)
    flaser = [i for i, ln in enumerate(lines) if ln.startswith("FLASER")]
    sparse = list(lines)
    for i in flaser:  # keep the first beam of each scan
        tokens = sparse[i].split()
        tokens[3 : 2 + 181] = ["nan"] * 180
        sparse[i] = " ".join(tokens)
    result = _invoke(str(write_log(tmp_path / "sparse.log", sparse)), "--out", str(tmp_path / "a"))
    assert result.exit_code == 1 and "too few valid ranges, 10 of 1810 readings (0.6%)" in result.output
    one = [_flaser_fields(ln, ranges="nan") if i in flaser[1:] else ln for i, ln in enumerate(lines)]
    result = _invoke(str(write_log(tmp_path / "one.log", one)), "--out", str(tmp_path / "b"))
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("far", ["1e7", "-3e12", "1e300"])
def test_a_far_pose_names_its_line_instead_of_a_memory_error(tmp_path, far):
    """One pose at x = 1e7 asked for a 60 GiB grid (MemoryError); now the line is named before allocating."""
    lines = room_log_lines(n_scans=10, n_beams=181)
    k = [i for i, ln in enumerate(lines) if ln.startswith("FLASER")][6]
    lines[k] = _flaser_fields(lines[k], x=far)
    log, out = write_log(tmp_path / "far.log", lines), tmp_path / "out"
    result = _invoke(str(log), "--out", str(out))
    assert result.exit_code == 1 and "Traceback" not in result.output and "unexpected" not in result.output
    assert "50,000,000 cells allowed" in result.output and f"line {k + 1}: pose ({float(far):.6g}" in result.output
    assert "correct or delete this line" in result.output and result.output.count("\n  - ") == 1
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*"))


def test_an_output_that_is_the_log_is_refused(tmp_path, room_log):
    before = room_log.read_bytes()
    result = _invoke(str(room_log), "--out", str(room_log), "--force")
    assert result.exit_code == 1 and "is the input" in result.output and room_log.read_bytes() == before


def test_a_map_too_large_for_its_resolution_names_the_setting(tmp_path, room_log):
    """No pose is an outlier: the fix is a coarser resolution (here 0.2 mm cells: 1.2e9 of them), not a line."""
    result = runner.invoke(app, ["ingest-log", str(room_log), "--out", str(tmp_path / "out"), "--config", "ci",
                                 "--set", "ingest_log.mapping.resolution=0.0002"])
    assert result.exit_code == 1 and "50,000,000 cells allowed" in result.output and "line " not in result.output
    assert "the trajectory spans 4 x 2 m" in result.output and "ingest_log.mapping.resolution" in result.output
