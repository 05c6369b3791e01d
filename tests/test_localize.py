"""`siteloc localize` end to end on a generated log: outputs, metrics, tracking accuracy, clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.config import load_config
from pipeline.ingest_log import run_ingest_log
from pipeline.io import tables
from stages.app import app
from tests.fixtures.carmen_logs import room_log_lines, write_log

runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("loc")
    log = write_log(root / "room-corrected.log", room_log_lines(80))
    return run_ingest_log(load_config("ci"), inputs={"log": log}, outputs={"out": root / "room"}, progress=False)


def test_tracking_replay_writes_estimates_metrics_and_plots(dataset, tmp_path):
    out = tmp_path / "out"
    res = runner.invoke(app, ["localize", str(dataset), "--out", str(out), "--init", "pose", "--trials", "2",
                              "--config", "ci", "--set", "filter.max_particles=800"])
    assert res.exit_code == 0, res.output
    est = tables.read_table(out / "estimates.parquet", "estimates").to_pydict()
    assert len(est["step"]) == 2 * 80 and set(est["trial"]) == {0, 1}
    err = np.array(est["error_xy"])
    # Odometry is noisy and the room is a bare rectangle: the laser must keep the filter within a few cm.
    assert np.median(err) < 0.1 and np.max(err[10:]) < 0.3
    m = json.loads((out / "metrics.json").read_text())
    s = m["summary"]["room-corrected"]
    assert s["trials"] == 2 and s["converged"] == 2 and m["init"] == "pose"
    assert {"error_median_m", "error_p90_m", "converged_step", "update_ms_mean"} <= set(m["runs"]["room-corrected"][0])
    for png in ("room-corrected_error.png", "room-corrected_map.png", "error_cdf.png"):
        assert (out / "plots" / png).stat().st_size > 1000
    assert (out / "config.yaml").is_file() and "converged" in res.output
    # The TUM files hold the estimates and the truth; evo's APE on them is the metrics' APE.
    from evo.core import metrics as evo_metrics
    from evo.tools.file_interface import read_tum_trajectory_file

    trial1 = np.array(est["trial"]) == 1
    mine = read_tum_trajectory_file(out / "trajectories" / "room-corrected_trial1.tum")
    truth = read_tum_trajectory_file(out / "trajectories" / "room-corrected_groundtruth.tum")
    np.testing.assert_allclose(mine.positions_xyz[:, 0], np.array(est["x"])[trial1])
    np.testing.assert_allclose(truth.positions_xyz[:, 1], np.array(est["gt_y"])[trial1])
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((truth, mine))
    assert m["runs"]["room-corrected"][1]["evo"]["ape_m"]["rmse"] == pytest.approx(ape.get_statistic(
        evo_metrics.StatisticsType.rmse), abs=1e-4)
    assert m["runs"]["room-corrected"][1]["evo"]["ape_m"]["median"] == pytest.approx(np.median(err[trial1]), abs=1e-4)


def test_bad_options_fail_clearly(dataset, tmp_path):
    res = runner.invoke(app, ["localize", str(dataset), "--out", str(tmp_path / "a"), "--init", "magic"])
    assert res.exit_code == 2 and all(f"'{c}'" in res.output for c in ("magic", "uniform", "pose", "candidates"))
    res = runner.invoke(app, ["localize", str(dataset), "--out", str(tmp_path / "b"), "--run", "nope"])
    assert res.exit_code == 1 and "room-corrected" in res.output
    res = runner.invoke(app, ["localize", str(dataset), "--out", str(tmp_path / "c"), "--kidnap-at", "20",
                              "--init", "pose"])
    assert res.exit_code == 1 and "kidnap-min-jump" in res.output and "Traceback" not in res.output
    (tmp_path / "not-a-log").mkdir()
    res = runner.invoke(app, ["localize", str(tmp_path / "not-a-log"), "--out", str(tmp_path / "d")])
    assert res.exit_code == 1 and "map.yaml" in res.output
    assert not any((tmp_path / n).exists() for n in "abcd")
