"""Recordings as robots write them (tests/fixtures/robot_recordings.py): localized, or refused by name.

Three recordings carry every trait of issue 52 between them; each is localized from the first true pose
and measured against the truth the generator returns (not against what the reader made of the file).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import ConfigError, InputError, OutputExistsError, OutputOverlapsInputError
from pipeline.io import tables
from pipeline.runtime.motion import compose2d
from tests.fixtures.robot_recordings import Traits, floor_map, record, write_map_yaml

CFG = load_config("demo")
SECONDS = 35.0
#: Traits of three recordings: every trait of issue 52 is in one of them.
MIXES = {
    "ros2_rplidar": Traits(fmt="mcap", laser_yaw_deg=90.0, laser_xy=(-0.05, 0.08), base_footprint_above=True,
                           odometry="both", odom_topic_drift=0.05, no_return="zero", below_min_share=0.05,
                           beam_jitter=2, rate_hz=40.0, bursts_and_gaps=True, odom_origin=(1000.0, -500.0, 1.0),
                           reference=False, seconds=SECONDS),
    "ros1_hokuyo": Traits(fmt="bag", slash=True, legacy_tf=True, laser_upside_down=True, laser_yaw_deg=180.0,
                          clockwise=True, no_return="nan", odometry="topic", rate_hz=5.0, base_frame="base_footprint",
                          fov_deg=270.0, beams=541, seconds=SECONDS),
    "db3_mirrored": Traits(fmt="db3", laser_upside_down=True, laser_yaw_deg=90.0, no_return="beyond",
                           seconds=SECONDS),
}


def _path(root, name, traits):
    return root / (f"{name}.bag" if traits.fmt == "bag" else name)


@pytest.fixture(scope="module")
def floor(tmp_path_factory):
    root = tmp_path_factory.mktemp("robots")
    occ = floor_map(0.05)
    return root, occ, write_map_yaml(root / "map.yaml", occ)


def _localize(root, rec, map_yaml, name, **kw):
    from pipeline.rosbag.replay import run_localize_bag

    out = run_localize_bag(CFG, inputs={"bag": rec.path, "map": map_yaml}, outputs={"out": root / f"out_{name}"},
                           progress=False, **kw)
    e = tables.read_table(out / "estimates.parquet", "estimates").to_pydict()
    pose = np.column_stack([e["x"], e["y"], e["theta"]])
    return out, pose, e, json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("name", list(MIXES))
def test_each_mix_of_traits_tracks_from_the_first_true_pose(floor, name):
    root, occ, map_yaml = floor
    traits = MIXES[name]
    rec = record(_path(root, name, traits), occ, traits)
    out, pose, e, doc = _localize(root, rec, map_yaml, name, init="pose", start_pose=tuple(rec.gt[0]))
    # The bursts' duplicate-free scans are all steps: a step per scan (duplicates within 1 us dropped).
    assert len(pose) == len(rec.stamps)
    err = np.hypot(*(pose[:, :2] - rec.gt[:, :2]).T)
    turn = np.degrees(np.abs(np.angle(np.exp(1j * (pose[:, 2] - rec.gt[:, 2])))))
    assert np.median(err) <= 0.05 and np.percentile(err, 90) <= 0.15, (np.median(err), np.percentile(err, 90))
    assert np.median(turn) <= 2.0
    q = doc["runs"][rec.path.stem if traits.fmt == "bag" else name][0]["quality"]
    assert q["converged"] and not q["lost_steps"] and q["agreement_median"] >= 0.9
    notes = " | ".join(doc["notes"])
    if traits.odometry == "both":  # tf is used; /odom drifts 5 cm per metre: said, with how far
        assert "odometry from /tf (odom -> base); /odom disagrees by up to" in notes and "is not used" in notes
    if traits.odometry == "topic":
        assert "odometry from /odom" in notes
    if traits.laser_upside_down:
        assert "mounted upside down: its scans are mirrored" in notes
    if traits.beam_jitter:
        assert "were resampled onto the first scan's beams" in notes
    if not traits.reference:
        assert "no reference" in notes and all(v is None or math.isnan(v) for v in e["error_xy"])
    else:
        assert doc["summary"][rec.path.stem]["error_median_m"] <= 0.05
    assert (out / "plots" / f"{rec.path.stem}_overview.png").stat().st_size > 10_000


def test_what_the_reader_makes_of_an_upside_down_clockwise_laser_is_what_an_upright_one_sees(floor, tmp_path):
    """Scans read back (mirrored, reversed) equal a cast from the true laser pose with the upright mount."""
    from pipeline.rosbag.drive import BagOptions, extract_drive, laser_of
    from pipeline.rosbag.read import read_recording
    from pipeline.sitegen.laser import LaserScanner

    _, occ, _ = floor
    traits = Traits(fmt="bag", slash=True, legacy_tf=True, laser_upside_down=True, laser_yaw_deg=90.0,
                    laser_xy=(0.2, -0.1), clockwise=True, fov_deg=270.0, beams=271, seconds=8.0)
    rec = record(tmp_path / "r.bag", occ, traits)
    got = read_recording(rec.path)
    drive = extract_drive(got, [0.0], BagOptions(), 10.0, use_stops=False)
    laser, _ = laser_of(got, BagOptions())
    assert math.isclose(laser.mount.yaw_deg, 90.0, abs_tol=1e-6) and math.isclose(laser.mount.x, 0.2)
    scanner = LaserScanner(occ, beams=laser.beams, fov_deg=laser.angle_max_deg - laser.angle_min_deg,
                           angle_min_deg=laser.angle_min_deg, range_max=traits.range_max, noise_sigma=0, dropout=0)
    mount = np.array([[laser.mount.x, laser.mount.y, math.radians(laser.mount.yaw_deg)]])
    want = scanner.cast_many(compose2d(rec.gt, np.repeat(mount, len(rec.gt), 0)), noisy=False)
    ranges = drive.run["ranges"]
    both = np.isfinite(ranges) & (want < traits.range_max)
    assert both.mean() > 0.8
    assert np.median(np.abs(ranges[both] - want[both])) < 0.02
    # Without the mirroring the same scans would be far off: the check above can fail.
    assert np.median(np.abs(ranges[:, ::-1][both] - want[both])) > 0.3


def test_a_tilted_laser_is_refused_naming_the_mount(floor, tmp_path):
    import dataclasses

    from pipeline.rosbag.replay import run_localize_bag
    from tests.rosbag.bags import rewrite

    root, occ, map_yaml = floor
    rec = record(tmp_path / "r", occ, Traits(seconds=5.0))

    def tilt(topic, msg, t, w):
        if topic != "/tf_static":
            return [(topic, msg, t)]
        s = math.sin(math.radians(30) / 2)  # 30 deg about the laser's y axis
        q = w.msgs.T["geometry_msgs/msg/Quaternion"](x=0.0, y=s, z=0.0, w=math.cos(math.radians(30) / 2))
        trs = [dataclasses.replace(tr, transform=dataclasses.replace(tr.transform, rotation=q))
               for tr in msg.transforms]
        return [(topic, w.msgs.tf(trs), t)]

    bad = rewrite(rec.path, tmp_path / "tilted", tilt)
    with pytest.raises(InputError, match=r"tilted 30.0 deg from level"):
        run_localize_bag(CFG, inputs={"bag": bad, "map": map_yaml}, outputs={"out": tmp_path / "o"}, progress=False)
    assert not (tmp_path / "o").exists()


def test_uniform_start_without_reference_converges_by_the_quality_rule(floor, tmp_path):
    root, occ, map_yaml = floor
    traits = Traits(reference=False, laser_yaw_deg=90.0, seconds=70.0)
    rec = record(tmp_path / "r", occ, traits)
    _, pose, e, doc = _localize(tmp_path, rec, map_yaml, "u")
    q = doc["runs"]["r"][0]["quality"]
    assert q["converged"], q
    err = np.hypot(*(pose[:, :2] - rec.gt[:, :2]).T)
    assert np.all(err[q["converged_step"]:] < 0.5)  # the rule's convergence is a real one
    assert q["state_changes"][0] == {"step": 0, "from": None, "to": "relocalising"}
    assert any(c["to"] == "tracking" for c in q["state_changes"])


def test_starting_outside_the_map_and_poses_off_the_map_are_refused(floor, tmp_path):
    from pipeline.io.map_yaml import read_map, write_map
    from pipeline.rosbag.replay import run_localize_bag

    root, occ, map_yaml = floor
    rec = record(tmp_path / "r", occ, Traits(seconds=5.0))
    shifted = read_map(map_yaml)
    write_map(tmp_path / "far.yaml", type(shifted)(shifted.grid, shifted.resolution, 100.0, 100.0))
    with pytest.raises(InputError, match="starts outside the map"):
        run_localize_bag(CFG, inputs={"bag": rec.path, "map": tmp_path / "far.yaml"},
                         outputs={"out": tmp_path / "o1"}, progress=False)
    from pipeline.errors import RuntimeInputError

    with pytest.raises(RuntimeInputError, match=r"--pose.*expected a position on the map"):
        run_localize_bag(CFG, inputs={"bag": rec.path, "map": map_yaml}, outputs={"out": tmp_path / "o2"},
                         init="pose", start_pose=(-50.0, 3.0, 0.0), progress=False)
    with pytest.raises(ConfigError, match="--pose goes with --init pose"):
        run_localize_bag(CFG, inputs={"bag": rec.path, "map": map_yaml}, outputs={"out": tmp_path / "o3"},
                         start_pose=(2.0, 3.0, 0.0), progress=False)


@pytest.mark.parametrize("variant", ["turned", "scale_fine", "raw_coarse", "negate_padded"])
def test_map_variants_as_map_server_reads_them(tmp_path, variant):
    """Modes, negate, resolution, a map much larger than the drive, and an origin with a yaw: the estimates
    come back in the map frame (for the turned origin, the truth turned with it)."""
    res, pad, mode, negate, origin = {"turned": (0.05, 0.0, "trinary", 0, (3.0, -2.0, 0.6)),
                                      "scale_fine": (0.025, 0.0, "scale", 0, None),
                                      "raw_coarse": (0.1, 0.0, "raw", 0, None),
                                      "negate_padded": (0.05, 15.0, "trinary", 1, None)}[variant]
    occ = floor_map(res, pad)
    rec = record(tmp_path / "r", occ, Traits(reference=False, seconds=20.0))
    map_yaml = write_map_yaml(tmp_path / "map.yaml", occ, mode=mode, negate=negate, origin=origin)
    truth = rec.gt if origin is None else compose2d(np.repeat([origin], len(rec.gt), 0), rec.gt)
    out, pose, _, doc = _localize(tmp_path, rec, map_yaml, variant, init="pose", start_pose=tuple(truth[0]))
    err = np.hypot(*(pose[:, :2] - truth[:, :2]).T)
    assert np.median(err) <= 0.05, np.median(err)
    assert doc["runs"]["r"][0]["quality"]["converged"]


def test_write_bag_goes_through_the_output_guard(floor, tmp_path):
    from pipeline.rosbag.bagfile import open_reader
    from pipeline.rosbag.replay import run_localize_bag

    root, occ, map_yaml = floor
    rec = record(tmp_path / "rec", occ, Traits(seconds=6.0, reference=False))
    before = sorted((p.name, p.stat().st_size) for p in rec.path.iterdir())

    def run(out, bag, **kw):
        return run_localize_bag(CFG, inputs={"bag": rec.path, "map": map_yaml}, outputs={"out": tmp_path / out},
                                write_bag=bag, progress=False, **kw)

    mcap = next(rec.path.glob("*.mcap"))
    for target in (mcap, rec.path / "x.mcap"):  # onto or into the recording: never, even with --force
        with pytest.raises(OutputOverlapsInputError):
            run("o1", target, force=True)
    with pytest.raises(ConfigError, match="the same path"):
        run("same.mcap", tmp_path / "same.mcap")
    with pytest.raises(ConfigError, match="name a .mcap file"):
        run("o1", tmp_path / "folder")
    (tmp_path / "taken.mcap").write_bytes(b"mine")
    with pytest.raises(OutputExistsError):
        run("o1", tmp_path / "taken.mcap")
    assert (tmp_path / "taken.mcap").read_bytes() == b"mine" and not (tmp_path / "o1").exists()
    assert sorted((p.name, p.stat().st_size) for p in rec.path.iterdir()) == before
    out = run("o2", tmp_path / "o2" / "bags" / "replay.mcap")  # inside --out: written with it
    beside = run("o3", tmp_path / "beside.mcap")
    assert (out / "bags" / "replay.mcap").is_file() and (tmp_path / "beside.mcap").is_file()
    assert not list(beside.glob("replay*")) and not list(tmp_path.glob(".*tmp*"))
    with open_reader(tmp_path / "beside.mcap") as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        clouds = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                  if c.topic == "/siteloc/particles"]
    updated = tables.read_table(beside / "estimates.parquet", "estimates").column("updated").to_pylist()
    steps = len(updated)
    assert counts["/map"] == 1 and counts["/siteloc/pose"] == counts["/siteloc/scan"] == steps
    # the particles where the filter updated (and at the start): the set does not change in between
    assert counts["/siteloc/particles"] == sum(updated) + (not updated[0]) and all(0 < len(c.poses) <= 200
                                                                                   for c in clouds)


def test_ingest_bag_turns_a_laser_only_drive_into_runs(floor, tmp_path):
    from pipeline.io.site import read_site
    from pipeline.rosbag.ingest import run_ingest_bag

    _, occ, map_yaml = floor
    a = record(tmp_path / "bags" / "a", occ, Traits(seconds=6.0))
    record(tmp_path / "bags" / "b", occ, Traits(seconds=6.0, reference=False, laser_yaw_deg=180.0))
    out = run_ingest_bag(CFG, inputs={"bags": [tmp_path / "bags"], "map": map_yaml}, outputs={"out": tmp_path / "s"},
                         progress=False)
    site = read_site(out / "site.yaml")
    assert site.camera is None and site.laser.mount.yaw_deg == 0.0
    assert (out / "captures.csv").read_text().splitlines() == ["image,stop_id,view,x,y,theta,room,area"]
    rep = json.loads((out / "bag_report.json").read_text())
    assert rep["stops"] == 0 and set(rep["runs"]) == {"a", "b"}
    assert rep["recordings"]["a"]["reference"] and not rep["recordings"]["b"]["reference"]
    traj = (out / "runs" / "a" / "trajectory.csv").read_text().splitlines()
    assert len(traj) == 1 + len(a.stamps)
    first = dict(zip(traj[0].split(","), traj[1].split(","), strict=True))
    assert math.isclose(float(first["gt_x"]), a.gt[0, 0], abs_tol=0.02)


def test_cli_localizes_a_laser_only_recording_from_a_pose(floor, tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    root, occ, map_yaml = floor
    rec = record(tmp_path / "take2", occ, Traits(seconds=16.0, reference=False))  # 6.4 m: 32 filter updates
    x, y, th = rec.gt[0]
    args = ["localize", "--bag", str(rec.path), "--map", str(map_yaml), "--out", str(tmp_path / "o"), "--init",
            "pose", "--write-bag", str(tmp_path / "o" / "replay.mcap")]
    res = CliRunner().invoke(app, [*args, "--pose", f"{x},{y},{math.degrees(th)}", "--frame", "base=base_link",
                                   "--topic", "scan=/scan"])
    assert res.exit_code == 0, res.output
    assert "no reference" in res.output and "yes (no reference)" in res.output
    assert (tmp_path / "o" / "replay.mcap").is_file()
    doc = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert np.allclose(doc["start_pose"], rec.gt[0])
    res = CliRunner().invoke(app, [*args, "--pose", "1,2", "--force"])
    assert res.exit_code == 1 and "expected X,Y,THETA" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(app, [*args, "--topic", "laser=/scan", "--force"])
    assert res.exit_code == 1 and "--topic roles ['laser'] unknown" in res.output
