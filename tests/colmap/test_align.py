"""The Sim3 fit against known transforms and a closed-form Umeyama, anchors parsing and their layout errors."""

from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest

from pipeline.colmap.align import (
    Anchor,
    align,
    cam_from_map,
    check_anchor_layout,
    fit_map_from_model,
    map_pose,
    read_anchors,
)
from pipeline.errors import InputError, Problems
from tests.colmap import random_sim3

XY = np.array([[1.0, 1.0], [2.0, 3.0], [4.0, 1.0], [5.0, 3.0], [3.0, 2.0]])


def umeyama(src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """Umeyama (1991) in closed form: the 3x4 [sR | t] minimising sum |tgt - (sR src + t)|^2."""
    mu_s, mu_t = src.mean(axis=0), tgt.mean(axis=0)
    a, b = src - mu_s, tgt - mu_t
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    scale = np.trace(np.diag(d) @ s) / a.var(axis=0).sum()
    return np.column_stack([scale * rot, mu_t - scale * rot @ mu_s])


@pytest.mark.parametrize("seed", range(5))
def test_fit_recovers_a_known_similarity(seed):
    rng = np.random.default_rng(seed)
    map_from_model = random_sim3(rng)
    height = rng.uniform(0.5, 2.0)  # the cameras' unknown height: absorbed by the translation
    map_xyz = np.column_stack([XY, np.full(len(XY), height)])
    model_xyz = map_from_model.inverse() * map_xyz
    fit = fit_map_from_model(model_xyz, XY)
    expected = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), np.array([0.0, 0.0, -height])) * map_from_model
    np.testing.assert_allclose(fit.matrix(), expected.matrix(), atol=1e-9)
    np.testing.assert_allclose(fit * model_xyz, np.column_stack([XY, np.zeros(len(XY))]), atol=1e-9)


def test_fit_is_the_least_squares_closed_form_with_noise():
    rng = np.random.default_rng(7)
    map_from_model = random_sim3(rng)
    model_xyz = map_from_model.inverse() * np.column_stack([XY, np.full(len(XY), 1.2)])
    model_xyz += rng.normal(scale=0.01, size=model_xyz.shape)
    fit = fit_map_from_model(model_xyz, XY)
    closed = umeyama(model_xyz, np.column_stack([XY, np.zeros(len(XY))]))
    np.testing.assert_allclose(np.asarray(fit.matrix()), closed, atol=1e-9)


def test_fit_works_when_the_model_origin_lies_in_the_cameras_plane():
    # A normalised COLMAP model has its origin at the camera centroid; estimate_sim3d alone refuses that.
    model_xyz = np.column_stack([XY - XY.mean(axis=0), np.zeros(len(XY))])
    assert pycolmap.estimate_sim3d(model_xyz, np.column_stack([XY, np.zeros(len(XY))])) is None
    fit = fit_map_from_model(model_xyz, XY)
    np.testing.assert_allclose(fit * model_xyz, np.column_stack([XY, np.zeros(len(XY))]), atol=1e-12)


def test_fit_of_collinear_points_is_refused():
    line = np.column_stack([np.arange(4.0), np.arange(4.0), np.zeros(4)])
    assert fit_map_from_model(line, line[:, :2] * 2) is None
    assert fit_map_from_model(line[:2], line[:2, :2]) is None


def test_heading_is_the_optical_axis_on_the_floor():
    for theta in (0.0, 0.5, math.pi / 2, -2.0, math.pi):
        centre, heading = map_pose(cam_from_map(1.0, 2.0, 1.5, theta), pycolmap.Sim3d())
        np.testing.assert_allclose(centre, [1.0, 2.0, 1.5], atol=1e-12)
        assert abs(math.remainder(heading - theta, 2 * math.pi)) < 1e-12
    # COLMAP's convention: the camera looks along +z, x right, y down.
    rot = np.asarray(cam_from_map(0.0, 0.0, 0.0, 0.0).rotation.matrix())
    np.testing.assert_allclose(rot.T @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # optical axis along map +x
    np.testing.assert_allclose(rot.T @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # image down is map down
    np.testing.assert_allclose(rot.T @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # image right is the camera's right
    looking_down = pycolmap.Rigid3d(pycolmap.Rotation3d(np.diag([1.0, -1.0, -1.0])), np.zeros(3))
    assert map_pose(looking_down, pycolmap.Sim3d())[1] is None


def test_align_reports_anchor_residuals():
    rng = np.random.default_rng(3)
    map_from_model = random_sim3(rng)
    model_from_map = map_from_model.inverse()
    thetas = [0.0, 1.0, 2.0, -1.0, 3.0]
    poses = {
        f"a{i}.png": model_from_map.transform_camera_world(cam_from_map(x, y, 0.0, t))
        for i, ((x, y), t) in enumerate(zip(XY, thetas, strict=True))
    }
    wrong = math.radians(10.0)  # one anchor's heading is off by 10 degrees, another's position by 0.2 m
    anchors = [
        Anchor(i + 2, f"a{i}.png", x + (0.2 if i == 4 else 0.0), y, t + (wrong if i == 1 else 0.0))
        for i, ((x, y), t) in enumerate(zip(XY, thetas, strict=True))
    ]
    result = align(poses, anchors[:4], fit=True)
    np.testing.assert_allclose(result.map_from_model.matrix(), map_from_model.matrix(), atol=1e-9)
    summary = result.summary()
    assert summary["position_error_m"]["max"] < 1e-9
    assert summary["heading_error_deg"]["max"] == pytest.approx(10.0)
    assert summary["anchors"][1]["heading_error_deg"] == pytest.approx(10.0)
    moved = align(poses, anchors, fit=True).summary()
    assert 0.05 < moved["position_error_m"]["max"] < 0.2
    identity = align(poses, anchors, fit=False).summary()
    assert identity["method"] == "none (--in-map-frame)" and identity["scale"] == 1.0


def test_read_anchors_matches_names_and_reports_bad_rows(tmp_path):
    path = tmp_path / "anchors.csv"
    path.write_text(
        "image,stop_id,x,y,theta\n"
        "images/a.png,s0,1,1,0\n"  # a site-relative path matches the COLMAP name a.png
        "b.png,s0,2,abc,0\n"
        "c.png,s0,2,2,inf\n"
        "nope.png,s0,1,1,0\n"
        "a.png,s0,1,1,0\n"
        "d.png,s1,3,1,0.5\n"
    )
    problems = Problems()
    anchors = read_anchors(path, {"a.png", "b.png", "c.png", "d.png"}, problems)
    assert [(a.image, a.line) for a in anchors] == [("a.png", 2), ("d.png", 7)]
    text = [str(p) for p in problems.items]
    assert "line 3: y 'abc' is not a number" in text[0]
    assert "line 4: theta is inf" in text[1]
    assert "line 5: image 'nope.png' is not in the COLMAP model" in text[2]
    assert "line 6: image 'a.png' is listed twice (first on line 2)" in text[3]


def test_read_anchors_needs_the_columns(tmp_path):
    path = tmp_path / "anchors.csv"
    path.write_text("image,x,y\na.png,1,1\n")
    problems = Problems()
    assert read_anchors(path, {"a.png"}, problems) == []
    assert "missing columns ['theta']" in str(problems.items[0])
    problems = Problems()
    read_anchors(tmp_path / "none.csv", set(), problems)
    assert "anchors file is missing" in str(problems.items[0])


@pytest.mark.parametrize(
    ("points", "message"),
    [
        ([(1, 1), (2, 3)], "2 usable anchors, the alignment needs at least 3"),
        ([(1, 1), (2, 2), (3, 3.01), (4, 4)], "lie on one line"),
        ([(1, 1), (1, 1), (1.01, 1)], "lie at one position"),
    ],
)
def test_anchor_layout_errors(tmp_path, points, message):
    anchors = [Anchor(i + 2, f"a{i}.png", x, y, 0.0) for i, (x, y) in enumerate(points)]
    problems = Problems()
    check_anchor_layout(tmp_path / "anchors.csv", anchors, 0.05, problems)
    with pytest.raises(InputError) as err:
        problems.raise_if_any("bad anchors")
    assert message in str(err.value)


def test_anchor_layout_accepts_a_triangle(tmp_path):
    problems = Problems()
    check_anchor_layout(
        tmp_path / "a.csv", [Anchor(2, "a", 1, 1, 0), Anchor(3, "b", 2, 3, 0), Anchor(4, "c", 4, 1, 0)], 0.05, problems
    )
    assert not problems
