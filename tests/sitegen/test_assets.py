"""Asset layer: real Sweet Home 3D models in the stated MODEL frame, the conversion cache, the fallback.

Tests needing the Debian files skip with the reason when they are absent; the synthetic-catalog tests build
a tiny `.sh3f` in tmp and always run, so the parser, the frame conversion and the cache are covered anyway.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.sitegen import assets, install_assets, obj_catalog
from pipeline.sitegen.asset_types import (
    ALLOWED_LICENSES,
    CLASSES,
    FURNITURE,
    AssetLibrary,
    AssetsUnavailableError,
    Model,
)

HAVE_REAL = bool(sorted(assets.default_furniture_dir().glob("*.sh3f"))) and (
    (assets.default_jar_source() / "SOURCE.json").is_file() or assets.default_jar_source().is_file()
)
needs_real = pytest.mark.skipif(
    not HAVE_REAL,
    reason="Sweet Home 3D assets absent: `sudo apt-get install sweethome3d-furniture` and "
    "`python -m pipeline.sitegen.install_assets` (make setup does both)",
)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, AssetLibrary]:
    """The real library converted from scratch into a fresh cache, once per module (~3 s)."""
    if not HAVE_REAL:
        pytest.skip("Sweet Home 3D assets absent (make setup installs them)")
    cache = tmp_path_factory.mktemp("assets-cache")
    library = assets.load_assets(cache_dir=cache, allow_fallback=False)
    return cache, library


def _all_models(library: AssetLibrary) -> list[Model]:
    return [m for items in library.models.values() for m in items]


def check_model(model: Model) -> None:
    """MODEL frame and array contracts (asset_types): what the renderer relies on."""
    assert model.parts, model.key
    pos = np.concatenate([p.positions for p in model.parts])
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    size = np.asarray(model.size)
    assert abs(lo[2]) < 1e-4, f"{model.key}: bottom at z={lo[2]}"
    assert np.all(np.abs((lo[:2] + hi[:2]) / 2) <= 0.01 * size[:2] + 1e-5), f"{model.key}: footprint not centred"
    np.testing.assert_allclose(hi - lo, size, rtol=0.02, atol=1e-4, err_msg=model.key)
    for part in model.parts:
        n = len(part.positions)
        assert n % 3 == 0 and n > 0
        assert part.positions.shape == (n, 3) and part.positions.dtype == np.float32
        assert part.normals.shape == (n, 3) and part.normals.dtype == np.float32
        assert part.uvs.shape == (n, 2) and part.uvs.dtype == np.float32
        for arr in (part.positions, part.normals, part.uvs):
            assert np.isfinite(arr).all(), model.key
        np.testing.assert_allclose(np.linalg.norm(part.normals, axis=1), 1.0, atol=1e-3, err_msg=model.key)
        if part.texture is not None:
            assert part.texture.dtype == np.uint8 and part.texture.ndim == 3 and part.texture.shape[2] == 3
            assert max(part.texture.shape[:2]) <= assets.ROLE_TEXTURE_PX
        assert all(0.0 <= c <= 1.0 for c in part.colour) and 0.0 < part.opacity <= 1.0
    assert model.n_triangles <= assets.MAX_TRIANGLES, model.key
    assert set(model.license.split(" AND ")) <= ALLOWED_LICENSES, model.license


# ------------------------------------------------------------------------------------------ real assets


@needs_real
def test_every_class_has_several_real_models(built):
    _, library = built
    assert not library.procedural and library.missing == []
    for cls in CLASSES:
        assert library.models[cls], cls
        assert all(m.cls == cls and not m.procedural for m in library.models[cls])
    for cls in ("chair", "door", "window", "plant"):
        assert len(library.models[cls]) >= 2, cls
    kinds = {m.kind for m in library.models[FURNITURE]}
    assert {"desk", "table", "cabinet"} <= kinds
    assert all(m.cls == "" for m in library.models[FURNITURE])
    assert library.model_for("door", "door_exterior", 0).kind == "door_exterior"
    assert library.model_for("", "desk", 7).kind == "desk"


@needs_real
def test_real_models_are_in_the_model_frame_at_catalog_size(built):
    _, library = built
    catalogs: dict[str, dict[str, obj_catalog.CatalogEntry]] = {}
    for model in _all_models(library):
        check_model(model)
        catalog, folder = model.key.split("/", 1)
        if catalog == assets.JAR:
            continue  # the jar's frame is resized to each poster picture
        if catalog not in catalogs:
            with zipfile.ZipFile(assets.default_furniture_dir() / f"{catalog}.sh3f") as zf:
                text = zf.read("PluginFurnitureCatalog.properties").decode("latin-1")
            catalogs[catalog] = {e.folder: e for e in obj_catalog.read_catalog(text, catalog)}
        entry = catalogs[catalog][folder]
        expected = np.array([entry.width_cm, entry.depth_cm, entry.height_cm]) / 100
        np.testing.assert_allclose(model.size, expected, rtol=0.02, err_msg=model.key)


@needs_real
def test_fronts_face_minus_y(built):
    """Beyond the bounding box: chair backs are at +y, the exit sign's sign and the posters' pictures face -y."""
    _, library = built
    for chair in library.models["chair"]:
        pos = np.concatenate([p.positions for p in chair.parts])
        assert pos[pos[:, 2] > 0.9 * chair.size[2], 1].mean() > 0.05, chair.key
    sign = library.models["exit_sign"][0]
    face = [p for p in sign.parts if p.texture is not None]
    assert face and face[0].normals[:, 1].mean() < -0.8
    for poster in library.models["poster"]:
        (picture,) = [p for p in poster.parts if p.role == "picture"]
        assert picture.texture is not None and picture.normals[:, 1].mean() < -0.99
    for model in library.models["door"] + library.models["window"]:
        y0, y1 = model.wall_span_y
        assert -model.size[1] / 2 - 1e-6 <= y0 < y1 <= model.size[1] / 2 + 1e-6, model.key


@needs_real
def test_real_textures_by_role(built):
    _, library = built
    for role, minimum in (("floor", 3), ("wall", 3), ("ceiling", 1), ("poster", 4)):
        images = library.textures[role]
        assert len(images) >= minimum and len(library.texture_info[role]) == len(images), role
        for image in images:
            assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
            assert max(image.shape[:2]) <= assets.ROLE_TEXTURE_PX and image.std() > 3  # a photograph, not flat
    posters = library.textures["poster"]
    for i in range(len(posters)):
        for j in range(i):
            assert posters[i].shape != posters[j].shape or not np.array_equal(posters[i], posters[j])
    assert all(info.tile_size_m for info in library.texture_info["floor"])


@needs_real
def test_licences_and_attribution(built):
    _, library = built
    for row in library.attribution:
        assert set(row["license"].split(" AND ")) <= ALLOWED_LICENSES, row
        assert row["creator"] and row["source"].startswith("Debian package sweethome3d"), row
    for infos in library.texture_info.values():
        assert all(set(i.license.split(" AND ")) <= ALLOWED_LICENSES for i in infos)
    used = {row["key"] for row in library.attribution if row["type"] == "model"}
    assert used == {m.key for m in _all_models(library)}
    text = install_assets.attribution_markdown(library)
    assert "Kator Legaz" in text and "CC0-1.0" in text and "CC-BY-3.0" in text


@needs_real
def test_cache_round_trip_is_identical_and_pickle_free(built):
    cache, library = built
    again = assets.load_assets(cache_dir=cache, allow_fallback=False)
    assert again.stats["converted"] == 0 and again.stats["from_cache"] == library.stats["converted"]
    for cls, models in library.models.items():
        assert [m.key for m in again.models[cls]] == [m.key for m in models]
        for a, b in zip(models, again.models[cls], strict=True):
            assert (a.name, a.creator, a.license, a.size, a.kind) == (b.name, b.creator, b.license, b.size, b.kind)
            for pa, pb in zip(a.parts, b.parts, strict=True):
                for name in ("positions", "normals", "uvs"):
                    assert np.array_equal(getattr(pa, name), getattr(pb, name))
                assert (pa.texture is None) == (pb.texture is None)
                if pa.texture is not None:
                    assert np.array_equal(pa.texture, pb.texture)
                assert (pa.colour, pa.opacity, pa.role) == (pb.colour, pb.opacity, pb.role)
    for role, images in library.textures.items():
        assert all(np.array_equal(x, y) for x, y in zip(images, again.textures[role], strict=True))
    index = json.loads((cache / "index.json").read_text())
    assert all(len(r["files_sha256"]) >= 1 for r in index["models"].values())
    files = sorted(cache.rglob("*.npz"))
    assert files
    for path in files:
        with np.load(path, allow_pickle=False) as data:
            assert all(data[name].dtype != object for name in data.files)


# ---------------------------------------------------------------------------------- synthetic catalog

PROPS = """# test catalog, latin-1 with escapes
id=test
name#1=Extinguisher
category#1=Miscellaneous
model#1=/blendswap-cc-0/fireExtinguisher/fireExtinguisher.obj
width#1=30
depth#1=20
height#1=60
creator#1=Test \\u00e9crivain
modelRotation#1=0 0 -1 0 1 0 1 0 0
elevation#1=10
"""

# A box 2 (x) x 1 (y) x 0.5 (z) in the raw file. modelRotation rows (0 0 -1 / 0 1 0 / 1 0 0) give SH3D
# (x, y, z) = (-z, y, x): raw y stays up, raw +x becomes the SH3D front (+z) = MODEL -y, raw -z becomes MODEL +x.
# The "marker" face is raw +x; the textured "photo" face is raw -z with v growing along raw y (up).
OBJ = """mtllib box.mtl
v -1 -0.5 -0.25
v 1 -0.5 -0.25
v 1 0.5 -0.25
v -1 0.5 -0.25
v -1 -0.5 0.25
v 1 -0.5 0.25
v 1 0.5 0.25
v -1 0.5 0.25
vt 0 0
vt 1 0
vt 1 1
vt 0 1
g body
usemtl grey
s off
f 1 2 6 5
f 4 8 7
f -5 -2 -6
f 5 6 7 8
f 1 5 8 4
usemtl photo
f 1/1 4/4 3/3 2/2
usemtl marker
f 2 3 7 6
"""

MTL = """newmtl grey
Kd 0.5 0.5 0.5
newmtl photo
Kd 0.64 0.64 0.64
map_Kd -s 1 1 1 tex.png
newmtl marker
Kd 1 0 0
"""


def _png() -> bytes:
    image = np.zeros((8, 4, 3), np.uint8)
    image[:4] = (255, 0, 0)  # top half red, bottom half blue
    image[4:] = (0, 0, 255)
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()


def _write_sh3f(path: Path, obj: str = OBJ) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("PluginFurnitureCatalog.properties", PROPS.encode("latin-1"))
        base = "blendswap-cc-0/fireExtinguisher/"
        zf.writestr(base + "fireExtinguisher.obj", obj)
        zf.writestr(base + "box.mtl", MTL)
        zf.writestr(base + "tex.png", _png())


def test_synthetic_catalog_conversion_frame_and_cache(tmp_path):
    furniture = tmp_path / "furniture"
    furniture.mkdir()
    _write_sh3f(furniture / "BlendSwap-CC-0.sh3f")
    kwargs = dict(cache_dir=tmp_path / "cache", furniture=False, furniture_dir=furniture, jar=tmp_path / "no-jar")
    with pytest.warns(assets.AssetFallbackWarning):  # no jar: textures are procedural
        library = assets.load_assets(("fire_extinguisher",), **kwargs)
    (model,) = library.models["fire_extinguisher"]
    assert not model.procedural and model.key == "BlendSwap-CC-0/fireExtinguisher"
    assert model.creator == "Test \u00e9crivain" and model.license == "CC0-1.0" and model.elevation == 0.1
    check_model(model)
    np.testing.assert_allclose(model.size, (0.3, 0.2, 0.6))
    parts = {tuple(round(c, 2) for c in p.colour): p for p in model.parts}
    marker = parts[(1.0, 0.0, 0.0)]
    np.testing.assert_allclose(marker.positions[:, 1], -0.1, atol=1e-6)  # raw +x became the front, -y
    np.testing.assert_allclose(marker.normals, np.tile([0, -1, 0], (len(marker.normals), 1)), atol=1e-6)
    (photo,) = [p for p in model.parts if p.texture is not None]
    assert photo.colour == (1.0, 1.0, 1.0) and photo.texture.shape == (8, 4, 3)
    np.testing.assert_allclose(photo.positions[:, 0], 0.15, atol=1e-6)  # raw -z became MODEL +x
    top = photo.positions[:, 2] > 0.3
    assert np.all(photo.uvs[top, 1] == 1.0) and np.all(photo.uvs[~top, 1] == 0.0)  # OBJ v up: v=1 at the top
    assert model.n_triangles == 2 + 1 + 1 + 2 + 2 + 2 + 2  # quads fanned, triangles kept, negative indices
    tri = model.parts[0].positions.reshape(-1, 3, 3)
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = np.einsum("ij,ij->i", face, tri.mean(axis=1) - [0, 0, 0.3])
    assert (outward > 0).all()  # counter-clockwise seen from outside after the rotation

    with pytest.warns(assets.AssetFallbackWarning):
        cached = assets.load_assets(("fire_extinguisher",), **kwargs)
    assert cached.stats["converted"] == 0 and cached.stats["from_cache"] == 1
    _write_sh3f(furniture / "BlendSwap-CC-0.sh3f", OBJ.replace("usemtl marker", "usemtl grey"))
    os.utime(furniture / "BlendSwap-CC-0.sh3f", ns=(1, 1))
    with pytest.warns(assets.AssetFallbackWarning):
        changed = assets.load_assets(("fire_extinguisher",), **kwargs)
    assert changed.stats["converted"] == 1  # the archive changed: converted again
    assert not any(p.colour == (1.0, 0.0, 0.0) for p in changed.models["fire_extinguisher"][0].parts)


def test_over_budget_model_is_skipped_for_a_stand_in(tmp_path, monkeypatch):
    furniture = tmp_path / "furniture"
    furniture.mkdir()
    _write_sh3f(furniture / "BlendSwap-CC-0.sh3f")
    monkeypatch.setattr(assets, "MAX_TRIANGLES", 5)
    with pytest.warns(assets.AssetFallbackWarning, match="fire_extinguisher"):
        library = assets.load_assets(("fire_extinguisher",), cache_dir=tmp_path / "c", furniture=False,
                                     furniture_dir=furniture, jar=tmp_path / "no-jar")
    assert library.stats["skipped"] == 1 and library.models["fire_extinguisher"][0].procedural


def test_java_properties_parser():
    text = "# c\n! c\nname#1=Frame H\\u00f4i An\nkey\\:x : a\\=b\ncont=one \\\n    two\nempty=\nlatin=caf\xe9\n"
    props = obj_catalog.parse_java_properties(text)
    assert props == {"name#1": "Frame H\u00f4i An", "key:x": "a=b", "cont": "one two", "empty": "",
                     "latin": "caf\xe9"}


# ------------------------------------------------------------------------------------------- fallback


def test_fallback_with_empty_sources_warns_and_covers_every_class(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.warns(assets.AssetFallbackWarning, match="procedural"):
        library = assets.load_assets(cache_dir=tmp_path / "cache", furniture_dir=empty, jar=empty)
    assert library.procedural and library.missing
    assert any("not found" in line for line in library.missing)
    for cls in CLASSES:
        assert library.models[cls] and all(m.procedural and m.cls == cls for m in library.models[cls]), cls
    for model in _all_models(library):
        check_model(model)
    for cls, kind in (("door", "door"), ("door", "door_exterior"), ("window", "window"), ("", "desk"),
                      ("", "table"), ("", "cabinet"), ("poster", "poster"), ("exit_sign", "exit_sign")):
        assert library.model_for(cls, kind, 3).kind == kind
    for role in ("floor", "wall", "ceiling", "poster"):
        assert library.textures[role] and all(t.dtype == np.uint8 and t.shape[2] == 3 for t in library.textures[role])
    assert len({t.tobytes() for t in library.textures["poster"]}) == len(library.textures["poster"])
    assert all(row["license"] == "CC0-1.0" for row in library.attribution)
    (picture,) = [p for p in library.models["poster"][0].parts if p.role == "picture"]
    assert picture.normals[:, 1].mean() < -0.99


def test_no_fallback_raises_with_the_install_hint(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AssetsUnavailableError, match="sweethome3d-furniture"):
        assets.load_assets(("chair",), cache_dir=tmp_path / "c", furniture_dir=empty, jar=empty, allow_fallback=False)
    with pytest.raises(ValueError, match="unknown classes"):
        assets.load_assets(("sofa",), cache_dir=tmp_path / "c", furniture_dir=empty, jar=empty)


# ------------------------------------------------------------------------------------- install_assets


def test_install_assets_without_apt_fails_clearly(tmp_path, monkeypatch, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("SITELOC_ASSETS", str(tmp_path / "root"))
    monkeypatch.setenv("SITELOC_SH3D_FURNITURE", str(empty))
    monkeypatch.delenv("SITELOC_SH3D_JAR", raising=False)
    monkeypatch.delenv("SITELOC_SKIP_ASSETS", raising=False)
    monkeypatch.setattr(assets, "SYSTEM_JAR", empty / "none.jar")
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert install_assets.main(["--no-build"]) == 1
    err = capsys.readouterr().err
    assert "apt-get install sweethome3d-furniture" in err and "apt-get/dpkg-deb not available" in err
    monkeypatch.setenv("SITELOC_SKIP_ASSETS", "1")
    assert install_assets.main([]) == 0


def test_extract_jar_keeps_only_resources(tmp_path, monkeypatch):
    jar = tmp_path / "sweethome3d.jar"
    with zipfile.ZipFile(jar, "w") as zf:
        zf.writestr(assets.JAR_TEXTURES + "roughcast.jpg", b"jpg")
        zf.writestr(assets.JAR_TEXTURE_CATALOG, "id=x\n")
        zf.writestr("com/eteks/sweethome3d/io/DefaultTexturesCatalog.class", b"\xca\xfe")
        zf.writestr("LICENSE.TXT", "GPL")
    dest = tmp_path / "root" / assets.JAR_DIRNAME
    assert install_assets.extract_jar(jar, dest, {"package": "sweethome3d"}) == 3
    assert (dest / assets.JAR_TEXTURES / "roughcast.jpg").read_bytes() == b"jpg"
    assert not (dest / "com/eteks/sweethome3d/io/DefaultTexturesCatalog.class").exists()
    source = json.loads((dest / "SOURCE.json").read_text())
    assert source["members"] == 3 and len(source["jar_sha256"]) == 64
    monkeypatch.setenv("SITELOC_ASSETS", str(tmp_path / "root"))
    monkeypatch.delenv("SITELOC_SH3D_JAR", raising=False)
    assert assets.default_jar_source() == dest
