"""`siteloc ingest-bag` and `siteloc export-bag` through the command line (typer's CliRunner)."""

from __future__ import annotations

import json
import re

import pytest
from typer.testing import CliRunner

from stages.app import app
from tests.fixtures.capture_site import write_capture_site
from tests.rosbag.bags import exported, truncated

runner = CliRunner()


def cli(*args: str):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    return exported(root)  # (site, bags)


def row(output: str, topic: str) -> list[str]:
    """The cells of the --list table's row for `topic`."""
    for line in output.splitlines():
        cells = [c.strip() for c in re.split(r"[│┃|]", line) if c.strip()]
        if cells and cells[0] == topic:
            return cells
    raise AssertionError(f"no row for {topic} in\n{output}")


def test_list_prints_topics_types_and_counts(tiny):
    _, bags = tiny
    res = cli("ingest-bag", bags, "--list")
    assert res.exit_code == 0, res.output
    out = res.output
    assert "capture: ros2 mcap" in out and "2021 messages" in out
    assert "query_a: ros2 mcap" in out and "188 messages" in out
    assert row(out, "/scan") == ["/scan", "sensor_msgs/msg/LaserScan", "9", "2.0", "scan"]
    cells = row(out, "/camera/image_raw/compressed")  # the first such row is capture's
    assert cells[1:3] == ["sensor_msgs/msg/CompressedImage", "24"] and cells[-1] == "camera"
    assert row(out, "/camera/camera_info")[1:3] == ["sensor_msgs/msg/CameraInfo", "24"]
    assert row(out, "/tf_static")[1:3] == ["tf2_msgs/msg/TFMessage", "1"]
    assert row(out, "/map")[1:] == ["nav_msgs/msg/OccupancyGrid", "1", "-", "map"]
    assert not list(bags.parent.glob("out*"))  # --list writes nothing


def test_ingest_of_a_bad_bag_is_an_error_not_a_traceback(tiny, tmp_path):
    _, bags = tiny
    cut = truncated(bags / "query_a", tmp_path / "cut" / "query_a")
    for args in (["ingest-bag", bags / "capture", cut, "--out", tmp_path / "out"], ["ingest-bag", cut, "--list"]):
        res = cli(*args)
        assert res.exit_code == 1, res.output
        assert "error:" in res.stderr and "cannot read the recording" in res.stderr
        assert "unreadable or truncated" in res.stderr
        assert "Traceback" not in res.output and "unexpected" not in res.output
    assert not (tmp_path / "out").exists()


def test_ingest_of_a_truncated_sqlite_bag_while_listing(tmp_path):
    """sqlite opens a bag cut near its end and fails only while reading: still a plain error."""
    _, bags = exported(tmp_path, "db3")
    cut = truncated(bags / "query_a", tmp_path / "cut" / "query_a", 0.99)
    res = cli("ingest-bag", cut, "--list")
    assert res.exit_code == 1
    assert "error:" in res.stderr and "truncated after" in res.stderr and "Traceback" not in res.output


def test_export_then_ingest(tmp_path):
    site = write_capture_site(tmp_path / "site")
    res = cli("export-bag", site, "--out", tmp_path / "bags", "--format", "bag")
    assert res.exit_code == 0, res.output
    assert f"output: {tmp_path / 'bags'}" in res.stdout
    assert re.search(r"capture: \d+ messages, [\d.]+ s, [\d.]+ MB -> .*capture\.bag", res.stdout)
    assert (tmp_path / "bags" / "query_a.bag").is_file()

    res = cli("ingest-bag", tmp_path / "bags", "--out", tmp_path / "back", "--annotations",
              site / "annotations.json")
    assert res.exit_code == 0, res.output
    assert "ingested 2 recordings: 4 stops, 1 runs" in res.stdout
    assert f"output: {tmp_path / 'back'}" in res.stdout
    rep = json.loads((tmp_path / "back" / "bag_report.json").read_text())
    assert rep["stops"] == 4 and rep["runs"]["query_a"]["steps"] == 9 and rep["annotations"]["images"] == 24

    res = cli("ingest-bag", tmp_path / "bags", "--out", tmp_path / "back")  # exists: refused without --force
    assert res.exit_code == 1 and "error:" in res.stderr and "Traceback" not in res.output
    res = cli("ingest-bag", tmp_path / "bags", "--out", tmp_path / "back", "--force")
    assert res.exit_code == 0, res.output


@pytest.mark.parametrize(("args", "message"), [
    (["--topic", "nonsense=x"], "--topic roles ['nonsense'] unknown; roles are ['camera', 'camera_info', 'scan', "
                                "'odom', 'map']"),
    (["--topic", "camera"], "--topic 'camera' must be ROLE=VALUE"),
    (["--time-offset", "camera=soon"], "--time-offset 'camera=soon': 'soon' is not a number of seconds"),
    (["--topic", "camera=/front/image_raw"], "--topic camera=/front/image_raw: no such topic"),
])
def test_bad_options_are_clear_errors(tiny, tmp_path, args, message):
    _, bags = tiny
    res = cli("ingest-bag", bags, "--out", tmp_path / "out", *args)
    assert res.exit_code == 1, res.output
    assert "error:" in res.stderr
    assert message in " ".join(res.stderr.split()), res.stderr
    assert "Traceback" not in res.output
    assert not (tmp_path / "out").exists()


def test_out_is_required(tiny):
    _, bags = tiny
    res = cli("ingest-bag", bags)
    assert res.exit_code == 1 and "--out is required (or --list to only look)" in res.stderr
