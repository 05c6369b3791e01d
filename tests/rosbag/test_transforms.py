"""TfBuffer against closed forms: interpolation, chains, inverses, gaps, the tree's shape; floor poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.rosbag.export import OPTICAL
from pipeline.rosbag.messages import yaw_quat
from pipeline.rosbag.transforms import TfBuffer, Transforms, from_floor_pose


def se3(yaw: float, xyz) -> np.ndarray:
    """4x4 of a rotation about z by `yaw` and a translation, written out."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = xyz
    return m


def matrices(tr: Transforms) -> np.ndarray:
    m = np.tile(np.eye(4), (len(tr.xyz), 1, 1))
    m[:, :3, :3] = tr.rot.as_matrix()
    m[:, :3, 3] = tr.xyz
    return m


def quat_of(matrix) -> tuple:
    return tuple(Rotation.from_matrix(np.asarray(matrix)[:3, :3]).as_quat())


def robot() -> TfBuffer:
    """map -> odom (1 Hz, drifting), odom -> base_link (4 Hz, driving an arc), base_link -> camera (static)."""
    tf = TfBuffer(max_gap=1.5, tolerance=0.05)
    for t in range(0, 11):
        tf.add("map", "odom", float(t), (1.0 + 0.01 * t, -2.0, 0.0), yaw_quat(0.3 + 0.02 * t), static=False)
    for k in range(0, 41):
        t = 0.25 * k
        tf.add("odom", "base_link", t, (0.5 * t, 0.1 * t * t, 0.0), yaw_quat(0.2 * t), static=False)
    tf.add("base_link", "camera", 0.0, (0.2, 0.0, 1.2), quat_of(OPTICAL), static=True)
    return tf


def test_interpolation_halfway_between_two_samples():
    tf = TfBuffer(max_gap=2.0)
    tf.add("odom", "base_link", 10.0, (0.0, 0.0, 0.0), yaw_quat(0.0), static=False)
    tf.add("odom", "base_link", 11.0, (2.0, 4.0, 1.0), yaw_quat(math.radians(90)), static=False)
    half = tf.lookup("odom", "base_link", [10.5])
    assert half.valid.tolist() == [True]
    assert half.xyz[0] == pytest.approx([1.0, 2.0, 0.5])  # the mean of the two translations
    assert half.rot.as_euler("zyx")[0] == pytest.approx([math.radians(45), 0.0, 0.0], abs=1e-12)  # slerp
    quarter = tf.lookup("odom", "base_link", [10.25])
    assert quarter.xyz[0] == pytest.approx([0.5, 1.0, 0.25])
    assert quarter.rot.as_euler("zyx")[0, 0] == pytest.approx(math.radians(22.5))
    exact = tf.lookup("odom", "base_link", [11.0])
    assert exact.rot.as_euler("zyx")[0, 0] == pytest.approx(math.radians(90)) and exact.xyz[0, 0] == 2.0


def test_slerp_takes_the_short_way_across_pi():
    tf = TfBuffer()
    tf.add("odom", "base_link", 0.0, (0, 0, 0), yaw_quat(math.radians(170)), static=False)
    tf.add("odom", "base_link", 0.2, (0, 0, 0), yaw_quat(math.radians(-170)), static=False)
    yaw = tf.lookup("odom", "base_link", [0.1]).floor_pose(0)[0, 2]
    assert abs(abs(yaw) - math.pi) < 1e-9  # 180 deg, not 0


def test_chained_lookup_is_the_product_of_the_edges():
    tf = robot()
    t = np.array([0.0, 2.6, 7.125, 10.0])
    got = matrices(tf.lookup("map", "camera", t))
    assert tf.lookup("map", "camera", t).valid.all()
    for i, s in enumerate(t):
        # x and yaw of both edges are linear in t, so interpolation reproduces them exactly; odom -> base_link's
        # y (0.1 t^2) is interpolated linearly between its quarter-second samples
        map_odom = se3(0.3 + 0.02 * s, (1.0 + 0.01 * s, -2.0, 0.0))
        a = 0.25 * min(math.floor(s / 0.25), 39)
        f = (s - a) / 0.25
        y = (1 - f) * 0.1 * a * a + f * 0.1 * (a + 0.25) ** 2
        odom_base = se3(0.2 * s, (0.5 * s, y, 0.0))
        base_cam = np.eye(4)
        base_cam[:3, :3], base_cam[:3, 3] = OPTICAL, (0.2, 0.0, 1.2)
        np.testing.assert_allclose(got[i], map_odom @ odom_base @ base_cam, atol=1e-12)


def test_inverse_lookup():
    tf = robot()
    t = np.array([1.0, 3.3, 9.9])
    fwd, back = tf.lookup("map", "camera", t), tf.lookup("camera", "map", t)
    for a, b in zip(matrices(fwd), matrices(back), strict=True):
        np.testing.assert_allclose(a @ b, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(b, np.linalg.inv(a), atol=1e-12)
    # between siblings: camera_from_laser = inv(base_from_camera) * base_from_laser
    tf.add("base_link", "laser", 0.0, (0.1, 0.0, 0.3), yaw_quat(0.0), static=True)
    cam_laser = matrices(tf.lookup("camera", "laser", [5.0]))[0]
    base_cam = np.eye(4)
    base_cam[:3, :3], base_cam[:3, 3] = OPTICAL, (0.2, 0.0, 1.2)
    np.testing.assert_allclose(cam_laser, np.linalg.inv(base_cam) @ se3(0.0, (0.1, 0.0, 0.3)), atol=1e-12)
    np.testing.assert_allclose(cam_laser[:3, 3], [0.0, 0.9, -0.1], atol=1e-12)  # 0.9 m below: +y (y points down)


def test_gaps_and_the_ends_of_the_recording():
    tf = TfBuffer(max_gap=0.5, tolerance=0.05)
    stamps = [0.0, 0.25, 0.5, 0.75, 1.0, 3.0, 3.25, 3.5]  # no sample from 1.0 to 3.0 s
    for s in stamps:
        tf.add("map", "odom", s, (s, 0.0, 0.0), yaw_quat(0.0), static=False)
    at = np.array([0.6, 1.0, 1.2, 2.0, 2.9, 3.1, 3.5, 3.54, 3.6, -0.04, -0.2])
    got = tf.lookup("map", "odom", at)
    assert got.valid.tolist() == [True, True, False, False, False, True, True, True, False, True, False]
    assert got.xyz[0, 0] == pytest.approx(0.6) and got.xyz[5, 0] == pytest.approx(3.1)
    assert got.xyz[7, 0] == pytest.approx(3.5)  # within tolerance beyond the end: the last sample
    assert tf.gaps("odom") == [(1.0, 3.0)]
    assert tf.gaps("odom", min_gap=3.0) == []
    wide = TfBuffer(max_gap=2.5)
    for s in stamps:
        wide.add("map", "odom", s, (s, 0.0, 0.0), yaw_quat(0.0), static=False)
    inside = wide.lookup("map", "odom", [2.0])
    assert inside.valid.tolist() == [True] and inside.xyz[0, 0] == pytest.approx(2.0)
    assert wide.gaps("odom") == []


def test_a_chain_is_invalid_where_any_edge_is():
    tf = robot()
    tf.edges.pop("odom")
    for t in (0.0, 1.0, 5.0, 6.0):  # map -> odom again, with a hole from 1 s to 5 s
        tf.add("map", "odom", t, (0.0, 0.0, 0.0), yaw_quat(0.0), static=False)
    got = tf.lookup("map", "camera", [0.5, 3.0, 5.5])
    assert got.valid.tolist() == [True, False, True]


def test_static_edges_hold_at_any_time_and_the_last_static_wins():
    tf = TfBuffer()
    tf.add("base_link", "laser", 5.0, (0.1, 0.0, 0.3), yaw_quat(0.0), static=True)
    tf.add("base_link", "laser", 6.0, (0.2, 0.0, 0.3), yaw_quat(0.0), static=True)
    got = tf.lookup("base_link", "laser", [-100.0, 0.0, 1e9])
    assert got.valid.all() and got.xyz[:, 0] == pytest.approx([0.2] * 3)


def test_two_parents_for_one_child():
    tf = TfBuffer()
    assert tf.add("odom", "base_link", 0.0, (0, 0, 0), yaw_quat(0), static=False) is None
    assert tf.add("/odom", "/base_link", 0.1, (0, 0, 0), yaw_quat(0), static=False) is None  # leading / is the same
    err = tf.add("world", "base_link", 0.2, (0, 0, 0), yaw_quat(0), static=False)
    assert err == "frame 'base_link' has two parents, 'odom' and 'world'"
    assert tf.edges["base_link"].parent == "odom" and len(tf.edges["base_link"].stamps) == 2


def test_unconnected_frames():
    tf = robot()
    tf.add("world", "elsewhere", 0.0, (0, 0, 0), yaw_quat(0), static=True)
    assert tf.path("map", "elsewhere") is None
    with pytest.raises(KeyError, match="no tf path from 'map' to 'elsewhere'"):
        tf.lookup("map", "elsewhere", [0.0])
    up, down = tf.path("map", "camera")
    assert up == ["camera", "base_link", "odom", "map"] and down == ["map"]


def test_floor_pose_of_an_optical_frame_gives_the_camera_yaw():
    yaws = np.radians([0.0, 30.0, 135.0, -100.0])
    map_base = from_floor_pose(np.column_stack([np.arange(4.0), -np.arange(4.0), yaws]))
    base_cam = Transforms(Rotation.from_matrix(np.repeat(OPTICAL[None], 4, axis=0)),
                          np.repeat([[0.3, 0.0, 1.2]], 4, axis=0), np.ones(4, bool))
    cam = (map_base * base_cam).floor_pose(2)  # z (forward) of the optical frame
    np.testing.assert_allclose(cam[:, 2], yaws, atol=1e-12)
    np.testing.assert_allclose(cam[:, 0], np.arange(4.0) + 0.3 * np.cos(yaws), atol=1e-12)
    np.testing.assert_allclose(cam[:, 1], -np.arange(4.0) + 0.3 * np.sin(yaws), atol=1e-12)
    x_axis = (map_base * base_cam).floor_pose(0)[:, 2]  # the optical x axis points to the right: yaw - 90 deg
    np.testing.assert_allclose(np.angle(np.exp(1j * (x_axis - yaws + math.pi / 2))), 0.0, atol=1e-12)
    # a camera pitched down 20 degrees still gives the yaw
    pitch = Rotation.from_euler("y", np.full((4, 1), math.radians(20)))
    tilted = Transforms(pitch * base_cam.rot, base_cam.xyz, base_cam.valid)
    np.testing.assert_allclose((map_base * tilted).floor_pose(2)[:, 2], yaws, atol=1e-12)
