"""The site renderer against closed forms: box silhouettes and depths by ray casting, projections, conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.errors import SitelocError
from pipeline.sitegen import render as render_mod
from pipeline.sitegen.camera import cam_from_map_rotation
from pipeline.sitegen.render import (
    Intrinsics,
    Lighting,
    Renderer,
    RenderError,
    RenderMesh,
    egl_available,
    lambert_irradiance,
    project_points,
)

_OK, _WHY = egl_available()
if not _OK:
    pytest.skip(f"no headless OpenGL here: {_WHY}", allow_module_level=True)

HFOV = math.radians(60)
EYE = 1.2  # camera height in metres


def checker(size: int = 64, squares: int = 8, a=(200, 60, 40), b=(40, 90, 200)) -> np.ndarray:
    ij = (np.arange(size) * squares // size)[:, None] + (np.arange(size) * squares // size)[None, :]
    return np.where((ij % 2 == 0)[..., None], np.array(a), np.array(b)).astype(np.uint8)


def box_mesh(lo, hi, *, instance_id: int = 0, texture=None, colour=(0.8, 0.8, 0.8), emissive: float = 0.0):
    """An axis-aligned box as a 12-triangle soup with per-face normals and uvs in metres."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    pos, nrm, uv = [], [], []
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for side in (0, 1):
            corner = lo.copy()
            corner[axis] = hi[axis] if side else lo[axis]
            du, dv = np.zeros(3), np.zeros(3)
            du[u_ax], dv[v_ax] = size[u_ax], size[v_ax]
            quad = [corner, corner + du, corner + du + dv, corner, corner + du + dv, corner + dv]
            st = [(0, 0), (1, 0), (1, 1), (0, 0), (1, 1), (0, 1)]
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            pos += quad
            nrm += [n] * 6
            uv += [(s * size[u_ax], t * size[v_ax]) for s, t in st]
    return RenderMesh(
        np.asarray(pos, np.float32),
        np.asarray(nrm, np.float32),
        np.asarray(uv, np.float32),
        texture,
        colour=colour,
        instance_id=instance_id,
        emissive=emissive,
    )


def pixel_rays(k: Intrinsics, map_from_cam, pitch: float = 0.0) -> np.ndarray:
    """Map-frame ray of every pixel centre, scaled to unit z-depth: (H, W, 3)."""
    cols, rows = np.meshgrid(np.arange(k.width), np.arange(k.height))
    cam = np.stack([(cols - k.cx) / k.fx, (rows - k.cy) / k.fy, np.ones_like(cols, float)], axis=-1)
    return cam @ cam_from_map_rotation(map_from_cam[3], pitch)  # rows of R are the cam axes in map: R^T c


def raycast_boxes(k: Intrinsics, map_from_cam, boxes, pitch: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form reference: (ids, z-depth) of the nearest box hit by each pixel-centre ray (slab test)."""
    rays = pixel_rays(k, map_from_cam, pitch)
    origin = np.asarray(map_from_cam[:3], float)
    ids = np.zeros(rays.shape[:2], np.uint32)
    depth = np.full(rays.shape[:2], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi, iid in boxes:
            t0 = (np.asarray(lo) - origin) / rays
            t1 = (np.asarray(hi) - origin) / rays
            near = np.nanmax(np.minimum(t0, t1), axis=-1)
            far = np.nanmin(np.maximum(t0, t1), axis=-1)
            hit = (near <= far) & (near > 0) & (near < depth)
            depth[hit] = near[hit]
            ids[hit] = iid
    return ids, depth


def edge_free(ids: np.ndarray) -> np.ndarray:
    """Pixels whose 8 neighbours have their id: where a 1 px rounding at silhouettes cannot matter."""
    pad = np.pad(ids, 1, mode="edge")
    same = np.ones(ids.shape, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            same &= pad[1 + dy : 1 + dy + ids.shape[0], 1 + dx : 1 + dx + ids.shape[1]] == ids
    return same


@pytest.fixture
def k160() -> Intrinsics:
    return Intrinsics.from_hfov(160, 120, HFOV)


def test_box_silhouette_matches_projected_corners_and_depth_is_closed_form(k160):
    lo, hi = (4.0, -0.5, 0.8), (4.6, 0.3, 1.6)
    pose = (0.0, 0.0, EYE, 0.0)
    with Renderer(k160) as renderer:
        renderer.set_scene([box_mesh(lo, hi, instance_id=5, texture=checker())])
        rgb, ids, depth = renderer.render(pose, Lighting())
    assert rgb.shape == (120, 160, 3) and rgb.dtype == np.uint8
    assert ids.dtype == np.uint32 and depth.dtype == np.float32
    assert set(np.unique(ids)) == {0, 5}
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    u, v, _ = project_points(k160, pose, corners)
    rows, cols = np.nonzero(ids == 5)
    # Pixel centres inside the silhouette: the drawn bounding box is the projected one, rounded inwards.
    assert abs(cols.min() - u.min()) <= 1 and abs(cols.max() - u.max()) <= 1
    assert abs(rows.min() - v.min()) <= 1 and abs(rows.max() - v.max()) <= 1
    # The front face is the plane x = 4: z-depth 4 m at its centre pixel, inf on the background.
    uc, vc, dc = project_points(k160, pose, np.array([[4.0, -0.1, 1.2]]))
    assert dc[0] == pytest.approx(4.0)
    assert depth[round(vc[0]), round(uc[0])] == pytest.approx(4.0, abs=0.01)
    assert np.isinf(depth[ids == 0]).all() and np.isfinite(depth[ids == 5]).all()
    assert (rgb[ids == 0] == 0).all() and rgb[ids == 5].mean() > 20


@pytest.mark.parametrize("pitch", [0.0, 0.15, -0.2])
def test_ids_and_depth_agree_with_ray_casting(k160, pitch):
    boxes = [((3.0, -1.0, 0.0), (3.8, 0.2, 1.1), 1), ((2.0, 0.6, 0.5), (2.5, 1.4, 2.2), 2)]
    pose = (0.3, -0.2, EYE, 0.1)
    with Renderer(k160) as renderer:
        renderer.set_scene([box_mesh(lo, hi, instance_id=i) for lo, hi, i in boxes])
        _, ids, depth = renderer.render(pose, Lighting(), pitch=pitch)
    ref_ids, ref_depth = raycast_boxes(k160, pose, boxes, pitch)
    inner = edge_free(ref_ids)
    assert (ids[inner] == ref_ids[inner]).all()
    assert (ids != ref_ids).mean() < 0.02  # only silhouette pixels may differ
    hit = inner & (ref_ids > 0)
    assert hit.sum() > 500
    np.testing.assert_allclose(depth[hit], ref_depth[hit], atol=0.01)
    project_u, project_v, _ = project_points(k160, pose, np.array([[3.0, -0.4, 0.5]]), pitch=pitch)
    assert ids[round(project_v[0]), round(project_u[0])] == 1


def test_nearer_box_hides_farther_one_exactly_where_expected(k160):
    far_box = ((6.0, -1.0, 0.2), (6.5, 1.0, 2.2), 2)
    near_box = ((3.0, -0.3, 0.9), (3.4, 0.3, 1.5), 1)
    pose = (0.0, 0.0, EYE, 0.0)
    with Renderer(k160) as renderer:
        renderer.set_scene([box_mesh(lo, hi, instance_id=i) for lo, hi, i in (far_box, near_box)])
        _, ids, depth = renderer.render(pose, Lighting())
    ref_ids, _ = raycast_boxes(k160, pose, [far_box, near_box])
    inner = edge_free(ref_ids)
    assert (ids[inner] == ref_ids[inner]).all()
    # The near box's silhouette is inside the far one's: a hole of id 1 surrounded by id 2.
    u, v, _ = project_points(k160, pose, np.array([[3.0, -0.3, 0.9], [3.0, 0.3, 1.5]]))
    rows, cols = np.nonzero(ids == 1)
    assert abs(cols.min() - u.min()) <= 1 and abs(cols.max() - u.max()) <= 1
    assert abs(rows.min() - v.min()) <= 1 and abs(rows.max() - v.max()) <= 1
    assert (ids[rows.min() - 3, cols.min() : cols.max() + 1] == 2).all()
    assert depth[ids == 1].max() < 3.5 and depth[ids == 2].min() >= 6.0 - 1e-3


def test_yaw_is_counter_clockwise_from_x_and_left_is_left(k160):
    target = box_mesh((-0.3, 4.7, 0.9), (0.3, 5.3, 1.5), instance_id=9)
    with Renderer(k160) as renderer:
        renderer.set_scene([target])
        _, ids_north, _ = renderer.render((0.0, 0.0, EYE, math.pi / 2), Lighting())
        _, ids_east, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting())
        # Looking along +x, the target moved to y = 1 (the camera's left) lands on the image's left half.
        renderer.set_scene([box_mesh((4.7, 0.7, 0.9), (5.3, 1.3, 1.5), instance_id=9)])
        _, ids_left, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting())
        # Higher up lands on the upper half (image y points down, map z up).
        renderer.set_scene([box_mesh((4.7, -0.3, 2.0), (5.3, 0.3, 2.6), instance_id=9)])
        _, ids_up, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting())
    rows, cols = np.nonzero(ids_north == 9)
    assert len(rows) > 50
    assert abs(cols.mean() - k160.cx) < 1.0 and abs(rows.mean() - k160.cy) < 1.0
    assert not (ids_east == 9).any()
    assert np.nonzero(ids_left == 9)[1].max() < k160.cx
    assert np.nonzero(ids_up == 9)[0].max() < k160.cy


def test_lighting_changes_rgb_never_ids_and_exposure_is_monotonic(k160):
    meshes = [
        box_mesh((-5, -5, -0.1), (15, 5, 0.0), instance_id=0, texture=checker(), colour=(0.5, 0.5, 0.5)),
        box_mesh((4.0, -0.5, 0.0), (4.6, 0.3, 1.6), instance_id=3, texture=checker(), colour=(0.6, 0.6, 0.6)),
    ]
    pose = (0.0, 0.0, EYE, 0.0)
    lights = ((3.0, 0.0, 2.6, 1.5), (5.0, 1.0, 2.6, 1.0))
    with Renderer(k160) as renderer:
        renderer.set_scene(meshes)
        base_rgb, base_ids, base_depth = renderer.render(pose, Lighting())
        runs = [
            Lighting(ambient=0.1, lights=lights),
            Lighting(ambient=0.3, lights=lights, tint=(1.0, 0.8, 0.6)),
            Lighting(ambient=0.0),
        ]
        for lighting in runs:
            rgb, ids, depth = renderer.render(pose, lighting)
            assert np.array_equal(ids, base_ids) and np.array_equal(depth, base_depth)
            assert not np.array_equal(rgb, base_rgb)
        means = [
            renderer.render(pose, Lighting(ambient=0.2, exposure=e))[0].astype(float).mean() for e in (0.3, 0.6, 1)
        ]
    assert means[0] < means[1] < means[2]


def test_emissive_stays_bright_without_lights(k160):
    sign = box_mesh((4.0, -0.5, 1.0), (4.1, 0.5, 1.4), instance_id=1, colour=(0.1, 0.9, 0.2), emissive=1.0)
    plain = box_mesh((4.0, 0.6, 1.0), (4.1, 1.6, 1.4), instance_id=2, colour=(0.1, 0.9, 0.2))
    with Renderer(k160) as renderer:
        renderer.set_scene([sign, plain])
        rgb, ids, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting(ambient=0.0, exposure=0.2))
    glow = rgb[ids == 1].astype(int)
    # Full-brightness albedo, sRGB-encoded: 0.9 -> ~243 in green.
    assert glow[:, 1].min() > 230 and glow[:, 0].max() < 100
    assert (rgb[ids == 2] == 0).all()


def test_shading_matches_closed_form_lambert(k160):
    floor = box_mesh((-5, -5, -0.1), (15, 5, 0.0), colour=(1.0, 1.0, 1.0))
    lighting = Lighting(ambient=0.1, lights=((3.0, 0.5, 2.5, 1.2), (6.0, -1.0, 2.5, 0.8)), exposure=0.9)
    pose = (0.0, 0.0, EYE, 0.0)
    with Renderer(k160) as renderer:
        renderer.set_scene([floor])
        rgb, _, depth = renderer.render(pose, lighting, pitch=-0.3)
    rays = pixel_rays(k160, pose, -0.3)
    for row, col in [(100, 80), (110, 20), (80, 140), (70, 70)]:
        point = np.asarray(pose[:3]) + depth[row, col] * rays[row, col]
        assert point[2] == pytest.approx(0.0, abs=0.01)
        linear = min(lambert_irradiance(point, (0, 0, 1), lighting) * lighting.exposure, 1.0)
        expected = 255 * linear ** (1 / render_mod.GAMMA)
        assert abs(float(rgb[row, col, 0]) - expected) < 3.0


def test_texture_orientation_follows_obj_uvs(k160):
    """uv (0, 0) is the image's bottom-left (OBJ/OpenGL), so a picture mapped with v up is drawn upright."""
    image = np.zeros((64, 64, 3), np.uint8)
    image[:, :, 2] = 255
    image[:32, :32] = (255, 0, 0)  # top-left quadrant of the picture (row 0 is the top)
    left, right, bottom, top = 0.5, -0.5, 0.8, 1.6  # y of the camera's left and right edge, z
    pos = np.array(
        [[4, left, bottom], [4, right, bottom], [4, right, top], [4, left, bottom], [4, right, top], [4, left, top]],
        np.float32,
    )
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 0], [1, 1], [0, 1]], np.float32)
    quad = RenderMesh(
        pos,
        np.tile([[-1.0, 0, 0]], (6, 1)).astype(np.float32),
        uvs,
        image,
        colour=(1, 1, 1),
        instance_id=1,
        emissive=1.0,
    )
    with Renderer(k160) as renderer:
        renderer.set_scene([quad])
        rgb, ids, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting())
    rows, cols = np.nonzero(ids == 1)
    r_mid, c_mid = (rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2
    red = rgb[..., 0] > 200
    assert red[ids == 1].mean() == pytest.approx(0.25, abs=0.05)
    red_rows, red_cols = np.nonzero(red)
    assert red_rows.max() < r_mid + 1 and red_cols.max() < c_mid + 1


def _cell_lights(grid, x: float, y: float) -> list[int]:
    """Decode the packed per-cell light list the way the fragment shader does."""
    ix, iy = (int(np.floor((v - o) / grid.cell)) for v, o in zip((x, y), grid.origin, strict=True))
    nx, ny = grid.dims
    if not (0 <= ix < nx and 0 <= iy < ny):
        return []
    header = int(grid.words[iy * nx + ix])
    slots = range(2 * nx * ny + (header >> 8), 2 * nx * ny + (header >> 8) + (header & 255))
    return [(int(grid.words[s >> 1]) >> (16 * (s & 1))) & 0xFFFF for s in slots]


@pytest.mark.parametrize("spacing, extent", [(2.5, 40.0), (2.0, 110.0)])
def test_light_grid_lists_every_light_in_reach(spacing, extent):
    xs = np.arange(0.0, extent, spacing)
    lights = tuple((float(x), float(y), 2.6, 1.0) for x in xs for y in xs[: len(xs) // 2])
    grid = render_mod.fit_light_grid(lights, 16384)
    assert len(grid.words) <= 16384
    if extent > 100:
        assert grid.cell > 1.0  # a large floor falls back to coarser cells to fit the uniform block
    rng = np.random.default_rng(0)
    arr = np.asarray(lights)
    for x, y, z in rng.uniform([-8, -8, 0], [extent + 8, extent / 2 + 8, 2.7], (300, 3)):
        in_reach = set(np.flatnonzero(np.linalg.norm(arr[:, :3] - (x, y, z), axis=1) < render_mod.LIGHT_RANGE_M))
        assert in_reach <= set(_cell_lights(grid, x, y))


def test_many_lights_shade_like_the_closed_form(k160):
    floor = box_mesh((-20, -20, -0.1), (40, 20, 0.0), colour=(1.0, 1.0, 1.0))
    lights = tuple((float(x), float(y), 2.6, 0.25) for x in np.arange(-10, 30, 2.5) for y in np.arange(-10, 10, 2.5))
    lighting = Lighting(ambient=0.05, lights=lights)
    pose = (0.0, 0.0, EYE, 0.0)
    with Renderer(k160) as renderer:
        renderer.set_scene([floor])
        rgb, _, depth = renderer.render(pose, lighting, pitch=-0.25)
    rays = pixel_rays(k160, pose, -0.25)
    for row, col in [(119, 0), (100, 80), (90, 150), (70, 10), (66, 80)]:
        point = np.asarray(pose[:3]) + depth[row, col] * rays[row, col]
        linear = min(lambert_irradiance(point, (0, 0, 1), lighting), 1.0)
        assert abs(float(rgb[row, col, 1]) - 255 * linear ** (1 / render_mod.GAMMA)) < 3.0


def test_same_call_twice_is_identical(k160):
    meshes = [
        box_mesh((3, -1, 0), (4, 1, 1), instance_id=1, texture=checker()),
        box_mesh((6, -2, 0), (7, 0, 2), instance_id=2, texture=checker(a=(10, 200, 10))),
    ]
    lighting = Lighting(lights=((4.0, 0.0, 2.5, 1.0),))
    with Renderer(k160) as renderer:
        renderer.set_scene(meshes)
        first = renderer.render((0.0, 0.2, EYE, 0.05), lighting, pitch=0.05)
        second = renderer.render((0.0, 0.2, EYE, 0.05), lighting, pitch=0.05)
    for a, b in zip(first, second, strict=True):
        assert np.array_equal(a, b)


def test_off_centre_principal_point_and_non_square_pixels_shift_as_projected():
    box = box_mesh((4.0, -0.4, 0.9), (4.4, 0.4, 1.5), instance_id=4)
    corners = np.array([[4.0, y, z] for y in (-0.4, 0.4) for z in (0.9, 1.5)])
    pose = (0.0, 0.0, EYE, 0.0)
    centred = Intrinsics(160, 120, 140.0, 140.0, 79.5, 59.5)
    shifted = Intrinsics(160, 120, 140.0, 110.0, 79.5 + 17.0, 59.5 - 11.0)
    results = {}
    with Renderer(centred) as renderer:
        renderer.set_scene([box])
        results[centred] = renderer.render(pose, Lighting())[1]
    with Renderer(shifted) as renderer:
        renderer.set_scene([box])
        results[shifted] = renderer.render(pose, Lighting())[1]
    for k, ids in results.items():
        u, v, _ = project_points(k, pose, corners)
        rows, cols = np.nonzero(ids == 4)
        assert abs(cols.min() - u.min()) <= 1 and abs(cols.max() - u.max()) <= 1
        assert abs(rows.min() - v.min()) <= 1 and abs(rows.max() - v.max()) <= 1
    # The same fx and an integer shift of cx: the columns move by exactly 17 px.
    cols_a = np.nonzero(results[centred] == 4)[1]
    cols_b = np.nonzero(results[shifted] == 4)[1]
    assert cols_b.min() - cols_a.min() == 17 and cols_b.max() - cols_a.max() == 17


def test_msaa_antialiases_rgb_but_keeps_ids_exact(k160):
    meshes = [box_mesh((3, -1, 0), (4, 1, 1), instance_id=1), box_mesh((6, -2, 0.5), (7, 0, 2), instance_id=7)]
    pose = (0.0, 0.0, EYE, 0.2)
    with Renderer(k160) as plain, Renderer(k160, samples=4) as msaa:
        plain.set_scene(meshes)
        msaa.set_scene(meshes)
        rgb_a, ids_a, depth_a = plain.render(pose, Lighting())
        rgb_b, ids_b, depth_b = msaa.render(pose, Lighting())
    assert np.array_equal(ids_a, ids_b) and np.array_equal(depth_a, depth_b)
    assert set(np.unique(ids_b)) == {0, 1, 7}
    assert not np.array_equal(rgb_a, rgb_b)  # edges blended
    colour_key = rgb_a.astype(np.uint32) @ np.array([1, 256, 65536], np.uint32)
    # Away from silhouettes, creases between a box's faces and the image border (an edge can lie between a border
    # pixel's centre and the border, where no neighbour shows it).
    flat = edge_free(colour_key) & edge_free(ids_a)
    flat[[0, -1], :] = flat[:, [0, -1]] = False
    assert flat.mean() > 0.8
    assert np.abs(rgb_a[flat].astype(int) - rgb_b[flat]).max() <= 1


def test_meshes_sharing_a_texture_are_batched(k160):
    shared = checker()
    same_content = shared.copy()
    other = checker(a=(0, 0, 0))
    meshes = [box_mesh((3 + i, -1, 0), (3.5 + i, 1, 1), instance_id=i + 1, texture=shared) for i in range(5)]
    meshes += [box_mesh((3, 2, 0), (4, 3, 1), instance_id=10, texture=same_content)]
    meshes += [box_mesh((3, -3, 0), (4, -2, 1), instance_id=11, texture=other)]
    meshes += [box_mesh((9, -3, 0), (10, -2, 1), instance_id=12), box_mesh((9, 2, 0), (10, 3, 1), instance_id=13)]
    with Renderer(k160) as renderer:
        renderer.set_scene(meshes)
        assert len(renderer._batches) == 3  # shared/same content, other, flat colour
        assert renderer.triangle_count == 12 * len(meshes)
        _, ids, _ = renderer.render((0.0, 0.0, EYE, 0.0), Lighting())
    assert {1, 2, 10, 11, 12, 13} <= set(np.unique(ids).tolist())


def test_frustum_culling_does_not_change_the_image(k160):
    rng = np.random.default_rng(3)
    meshes = []
    for i in range(60):
        lo = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 0.0])
        meshes.append(box_mesh(lo, lo + rng.uniform(0.3, 1.5, 3), instance_id=i + 1, texture=checker()))
    with Renderer(k160) as renderer:
        renderer.set_scene(meshes)
        for yaw in np.linspace(-math.pi, math.pi, 7):
            pose = (0.5, -0.5, EYE, float(yaw))
            renderer.cull = True
            culled = renderer.render(pose, Lighting(lights=((0.0, 0.0, 2.5, 1.0),)))
            renderer.cull = False
            full = renderer.render(pose, Lighting(lights=((0.0, 0.0, 2.5, 1.0),)))
            for a, b in zip(culled, full, strict=True):
                assert np.array_equal(a, b)


def test_bad_mesh_and_missing_egl_raise_render_errors(k160, monkeypatch):
    with Renderer(k160) as renderer:
        bad = RenderMesh(np.zeros((4, 3), np.float32), np.zeros((4, 3), np.float32), np.zeros((4, 2)), None)
        with pytest.raises(RenderError, match="mesh 0: positions"):
            renderer.set_scene([bad])
    import moderngl

    def no_egl(*args, **kwargs):
        raise Exception("eglGetDisplay failed")

    monkeypatch.setattr(moderngl, "create_standalone_context", no_egl)
    with pytest.raises(SitelocError, match="libegl1 libgl1-mesa-dri libegl-mesa0") as info:
        Renderer(k160)
    assert "eglGetDisplay failed" in str(info.value)


def test_project_points_conventions():
    k = Intrinsics(100, 80, 50.0, 60.0, 49.5, 39.5)
    pose = (1.0, 2.0, 1.5, math.pi / 2)  # looking along +y
    u, v, depth = project_points(k, pose, np.array([[1.0, 5.0, 1.5], [0.0, 4.0, 1.5], [1.0, 4.0, 2.5], [1, 1, 1.5]]))
    assert (u[0], v[0], depth[0]) == pytest.approx((49.5, 39.5, 3.0))
    assert u[1] < 49.5  # -x is on the left when facing +y
    assert u[1] == pytest.approx(49.5 - 50.0 * 1.0 / 2.0)
    assert v[2] == pytest.approx(39.5 - 60.0 * 1.0 / 2.0)  # up is towards row 0
    assert np.isnan(u[3]) and depth[3] < 0  # behind the camera


def test_check_image_written_for_eyeballing(tmp_path):
    """A room of textured boxes under two lights, saved for a human look (and /tmp/render_check.png)."""
    from PIL import Image

    k = Intrinsics.from_hfov(320, 240, HFOV)
    meshes = [
        box_mesh((-1, -3, -0.1), (9, 3, 0.0), texture=checker(64, 8, (150, 150, 150), (90, 90, 90))),  # floor
        box_mesh((-1, -3, 2.7), (9, 3, 2.8), colour=(0.9, 0.9, 0.9)),  # ceiling
        box_mesh((9, -3, 0), (9.1, 3, 2.7), texture=checker(64, 2, (200, 190, 160), (180, 170, 140))),  # far wall
        box_mesh((-1, 3, 0), (9, 3.1, 2.7), colour=(0.7, 0.75, 0.8)),  # left wall (+y)
        box_mesh((-1, -3.1, 0), (9, -3, 2.7), colour=(0.8, 0.7, 0.6)),  # right wall (-y)
        box_mesh((4, 1.0, 0), (5, 2.0, 0.8), instance_id=1, texture=checker(a=(220, 30, 30), b=(250, 240, 240))),
        box_mesh((5, -2.0, 0), (5.6, -1.2, 1.8), instance_id=2, texture=checker(a=(30, 60, 220), b=(240, 240, 250))),
        box_mesh((8.8, -0.4, 2.0), (8.9, 0.4, 2.3), instance_id=3, colour=(0.1, 0.9, 0.2), emissive=1.0),
    ]
    lighting = Lighting(ambient=0.25, lights=((3.0, 0.0, 2.6, 1.2), (6.5, 0.0, 2.6, 1.2)))
    with Renderer(k, samples=4) as renderer:
        renderer.set_scene(meshes)
        rgb, ids, _ = renderer.render((0.0, 0.0, EYE, 0.0), lighting)
    # Red box (+y, the camera's left) on the left, blue box (-y) on the right, floor at the bottom.
    assert np.nonzero(ids == 1)[1].mean() < k.cx < np.nonzero(ids == 2)[1].mean()
    assert rgb[-5].mean() > 0 and np.nonzero(ids == 3)[0].mean() < k.cy
    Image.fromarray(rgb).save(tmp_path / "render_check.png")
    Image.fromarray(rgb).save("/tmp/render_check.png")
