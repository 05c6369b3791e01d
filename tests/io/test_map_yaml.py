"""ROS map_server YAML + PGM: round trip, map_server pixel semantics, origin at the lower-left pixel."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from pipeline.errors import InputError
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap, read_map, write_map


def random_grid(rng, h=30, w=40):
    return rng.choice(np.array([FREE, OCCUPIED, UNKNOWN], dtype=np.int8), size=(h, w))


def test_round_trip(tmp_path):
    grid = random_grid(np.random.default_rng(0))
    m = OccupancyMap(grid=grid, resolution=0.05, origin_x=-3.2, origin_y=1.5, origin_yaw=0.0)
    write_map(tmp_path / "map.yaml", m)
    back = read_map(tmp_path / "map.yaml")
    assert np.array_equal(back.grid, grid)
    assert (back.resolution, back.origin_x, back.origin_y) == (0.05, -3.2, 1.5)
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary"
    assert (tmp_path / "map.pgm").read_bytes()[:2] == b"P5"


def test_row_zero_is_the_bottom_of_the_image(tmp_path):
    grid = np.full((4, 5), FREE, dtype=np.int8)
    grid[0, 1] = OCCUPIED  # lowest y, second column
    write_map(tmp_path / "m.yaml", OccupancyMap(grid=grid, resolution=1.0))
    pixels = np.asarray(Image.open(tmp_path / "m.pgm"))
    assert pixels[-1, 1] == 0 and pixels[0, 1] == 254
    m = read_map(tmp_path / "m.yaml")
    assert m.value_at(1.5, 0.5) == OCCUPIED and m.value_at(1.5, 3.5) == FREE


@pytest.mark.parametrize("negate", [0, 1])
def test_map_server_thresholds(tmp_path, negate):
    values = np.arange(256, dtype=np.uint8).reshape(16, 16)
    Image.fromarray(values, mode="L").save(tmp_path / "g.pgm")
    (tmp_path / "g.yaml").write_text(
        yaml.safe_dump(
            {
                "image": "g.pgm",
                "resolution": 0.1,
                "origin": [0, 0, 0],
                "negate": negate,
                "occupied_thresh": 0.65,
                "free_thresh": 0.196,
            }
        )
    )
    m = read_map(tmp_path / "g.yaml")
    v = values[::-1].astype(float)
    p = v / 255 if negate else (255 - v) / 255  # map_server's occupancy probability
    expected = np.where(p > 0.65, OCCUPIED, np.where(p < 0.196, FREE, UNKNOWN))
    assert np.array_equal(m.grid, expected)


def test_scale_mode_keeps_intermediate_values(tmp_path):
    Image.fromarray(np.array([[0, 128, 254]], dtype=np.uint8), mode="L").save(tmp_path / "s.pgm")
    (tmp_path / "s.yaml").write_text(
        yaml.safe_dump({"image": "s.pgm", "resolution": 1, "origin": [0, 0, 0], "mode": "scale", "negate": 0})
    )
    grid = read_map(tmp_path / "s.yaml").grid
    assert grid[0, 0] == OCCUPIED and grid[0, 2] == FREE and 1 <= grid[0, 1] <= 99


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-20, 20),
    y=st.floats(-20, 20),
    yaw=st.floats(-math.pi, math.pi),
    ox=st.floats(-5, 5),
    oy=st.floats(-5, 5),
)
def test_world_cell_round_trip(x, y, yaw, ox, oy):
    m = OccupancyMap(grid=np.zeros((10, 10), dtype=np.int8), resolution=0.1, origin_x=ox, origin_y=oy, origin_yaw=yaw)
    row, col = m.world_to_cell(x, y)
    cx, cy = m.cell_to_world(row, col)
    # the centre of the cell holding a point is within half a diagonal of it
    assert math.hypot(cx - x, cy - y) <= 0.1 * math.sqrt(2) / 2 + 1e-9


@pytest.mark.parametrize(
    ("doc", "fragment"),
    [
        ({"image": "g.pgm", "resolution": 0.1}, "key 'origin': required key is missing"),
        ({"image": "g.pgm", "resolution": 0.1, "origin": [0, 0, 0], "colour": 1}, "key 'colour': unknown key"),
        ({"image": "g.pgm", "resolution": -1, "origin": [0, 0, 0]}, "key 'resolution'"),
        ({"image": "g.pgm", "resolution": 0.1, "origin": [0, 0]}, "key 'origin': must be [x, y, yaw]"),
        ({"image": "g.pgm", "resolution": 0.1, "origin": [0, 0, 0], "mode": "fancy"}, "key 'mode'"),
        ({"image": "nope.pgm", "resolution": 0.1, "origin": [0, 0, 0]}, "image 'nope.pgm' does not exist"),
    ],
)
def test_bad_map_yaml(tmp_path, doc, fragment):
    Image.fromarray(np.zeros((2, 2), dtype=np.uint8), mode="L").save(tmp_path / "g.pgm")
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError) as exc:
        read_map(tmp_path / "g.yaml")
    assert fragment in str(exc.value) and "g.yaml" in str(exc.value)


@pytest.mark.parametrize(("write", "words"), [
    (lambda p: Image.fromarray(np.full((4, 5), 1000, np.uint16)).save(p, format="PPM"),
     ["more than 8 bits", "convert it to 8-bit"]),  # maxval 65535: map_server reads 8-bit values
    (lambda p: p.write_bytes(b""), ["empty file"]),
    (lambda p: p.write_bytes(b"P5\n40 30\n255\n" + bytes(100)), ["truncated"]),
])
def test_a_map_image_that_is_not_8_bit_or_is_damaged_is_refused(tmp_path, write, words):
    write(tmp_path / "m.pgm")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"image": "m.pgm", "resolution": 0.1, "origin": [0, 0, 0]}))
    with pytest.raises(InputError) as info:
        read_map(tmp_path / "m.yaml")
    text = str(info.value)
    assert str(tmp_path / "m.pgm") in text and "unreadable map image" in text
    for word in words:
        assert word in text, text
