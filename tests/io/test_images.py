"""`pipeline.io.images`: valid 8-bit images decode to PIL's own pixels; what cannot be decoded faithfully
(empty, not an image, truncated, too large, 16-bit or float) is refused with an InputError naming the file
or message and the fix. Fixtures are a few pixels, written here; the bombs are PNG headers alone."""

from __future__ import annotations

import io
import pickle
import struct
import warnings
import zlib

import numpy as np
import pytest
from PIL import Image, ImageFile

from pipeline.errors import InputError, Problems
from pipeline.io.images import MAX_PIXELS, ImageError, image_rgb, image_size, open_image

RNG = np.random.default_rng(0)


def noise(h=24, w=32, channels=3) -> np.ndarray:
    return RNG.integers(0, 256, (h, w, channels) if channels else (h, w), dtype=np.uint8)


def encoded(image: Image.Image, fmt: str) -> bytes:
    buf = io.BytesIO()
    image.save(buf, format=fmt)
    return buf.getvalue()


def png_header(width: int, height: int) -> bytes:
    """A PNG that claims width x height RGB pixels and holds almost none: a bomb without the memory."""

    def chunk(cid: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + cid + data + struct.pack(">I", zlib.crc32(cid + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 16))
            + chunk(b"IEND", b""))


def refused(source, *words, name=None, **kw) -> ImageError:
    with pytest.raises(ImageError) as info:
        open_image(source, name=name, **kw)
    exc = info.value
    assert isinstance(exc, InputError)
    text = str(exc)
    label = name or str(source)
    assert label in text and exc.problems[0].file == label
    for word in words:
        assert word in text, text
    assert exc.problems[0].fix
    return exc


@pytest.mark.parametrize("mode", ["RGB", "L", "P", "LA", "RGBA", "CMYK", "1"])
def test_8_bit_images_give_the_pixels_of_pils_own_conversion(tmp_path, mode):
    image = Image.fromarray(noise(channels=4), "RGBA")
    image = image.convert(mode) if mode != "P" else image.convert("RGB").quantize(16)
    path = tmp_path / f"a.{'tiff' if mode == 'CMYK' else 'png'}"
    image.save(path)
    with Image.open(path) as ref:
        want = np.asarray(ref.convert("RGB"))
        ref_mode = ref.mode
    np.testing.assert_array_equal(image_rgb(path), want)
    got = open_image(path)
    assert got.mode == "RGB" and got.size == (32, 24)
    assert open_image(path, rgb=False).mode == ref_mode  # map_yaml reads grey and alpha from the own mode


def test_a_jpeg_decodes_as_pil_decodes_it(tmp_path):
    path = tmp_path / "a.jpg"
    Image.fromarray(noise()).save(path, quality=90)
    with Image.open(path) as ref:
        want = np.asarray(ref.convert("RGB"))
    np.testing.assert_array_equal(image_rgb(path), want)
    np.testing.assert_array_equal(image_rgb(path.read_bytes(), name="bag message 3"), want)
    assert image_size(path) == (32, 24)


@pytest.mark.parametrize(("array", "words"), [
    ((np.arange(24 * 32).reshape(24, 32) * 80).astype(np.uint16), ["16-bit", "I;16", "convert it to 8-bit"]),
    (np.zeros((24, 32), np.int32), ["more than 8 bits", "PIL mode I:", "convert it to 8-bit"]),
    (np.zeros((24, 32), np.float32), ["floating-point", "PIL mode F", "convert it to 8-bit"]),
])
def test_16_bit_integer_and_float_images_are_refused_not_clipped(tmp_path, array, words):
    path = tmp_path / ("a.png" if array.dtype == np.uint16 else "a.tiff")
    Image.fromarray(array).save(path)
    refused(path, *words)
    with pytest.raises(ImageError, match="8-bit"):
        image_size(path)  # the header says so: refused without decoding


def test_an_empty_file_is_refused(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"")
    refused(tmp_path / "a.jpg", "empty file")


def test_bytes_that_are_no_image_are_refused_and_quoted_escaped(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"\x1b[31mnot an image" + RNG.bytes(400))
    exc = refused(tmp_path / "a.jpg", "not an image PIL can identify", "\\x1b[31m")
    assert "\x1b" not in str(exc)


@pytest.mark.parametrize("fmt", ["JPEG", "PNG"])
def test_a_truncated_image_is_refused_when_decoded(tmp_path, fmt):
    data = encoded(Image.fromarray(noise(64, 64)), fmt)
    path = tmp_path / f"a.{fmt.lower()}"
    path.write_bytes(data[: len(data) // 2])
    assert not ImageFile.LOAD_TRUNCATED_IMAGES
    refused(path, "truncated", "copy it again")
    assert image_size(path) == (64, 64)  # the header alone is intact: only decoding finds the cut


def test_a_png_cut_inside_its_header_is_named_as_such(tmp_path):
    (tmp_path / "a.png").write_bytes(encoded(Image.fromarray(noise()), "PNG")[:20])
    refused(tmp_path / "a.png", "PNG file truncated or damaged in its header")


def test_a_missing_file_or_a_folder_is_refused(tmp_path):
    refused(tmp_path / "none.png", "cannot be read")
    refused(tmp_path, "cannot be read")


@pytest.mark.parametrize(("size", "words"), [
    ((50_000, 50_000), ["2,500,000,000 pixels"]),  # above twice PIL's limit: PIL itself refuses to open it
    ((10_000, 10_000), ["10000 x 10000"]),  # between PIL's limit and twice it: PIL would only warn
])
def test_decompression_bombs_are_refused_without_a_warning(tmp_path, size, words):
    path = tmp_path / "bomb.png"
    path.write_bytes(png_header(*size))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PIL's DecompressionBombWarning must not escape first
        refused(path, "decompression bomb", f"{MAX_PIXELS:,} pixels", *words)
        with pytest.raises(ImageError, match="decompression bomb"):
            image_size(path)
    assert Image.MAX_IMAGE_PIXELS == MAX_PIXELS  # PIL's global setting is left alone


def test_the_pixel_limit_is_a_parameter(tmp_path):
    path = tmp_path / "a.png"
    Image.fromarray(noise()).save(path)
    refused(path, "24 = 768 pixels", "more than 700 pixels", max_pixels=700)
    assert open_image(path, max_pixels=768).size == (32, 24)


def test_bytes_are_named_by_the_caller():
    data = encoded(Image.fromarray(noise(64, 64)), "JPEG")
    name = "run.mcap /camera/image/compressed message 7"
    refused(data[: len(data) // 2], "truncated image", name=name)
    refused(b"", "empty", name=name)
    assert image_size(bytearray(data), name=name) == (64, 64)


def test_the_error_survives_a_process_boundary(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"")
    exc = refused(tmp_path / "a.jpg")
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is ImageError and str(back) == str(exc) and back.problems == exc.problems


def test_the_ingest_check_collects_every_bad_image(tmp_path):
    from pipeline.io.captures import CaptureRow, check_images

    Image.fromarray(noise()).save(tmp_path / "good.png")
    (tmp_path / "empty.png").write_bytes(b"")
    Image.fromarray(np.zeros((24, 32), np.uint16)).save(tmp_path / "deep.png")
    data = encoded(Image.fromarray(noise(64, 64)), "JPEG")
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    rows = [CaptureRow(line, name, "s", 0, 0.0, 0.0, 0.0, "", "")
            for line, name in enumerate(["good.png", "empty.png", "deep.png", "cut.jpg"], start=2)]
    problems = Problems()
    out = check_images(tmp_path, tmp_path / "captures.csv", rows, None, True, problems, progress=False)
    assert list(out) == ["good.png"]
    assert [(p.row, p.message.split(":")[0]) for p in problems.items] == [
        (3, "image 'empty.png' is unreadable"), (4, "image 'deep.png' is unreadable"),
        (5, "image 'cut.jpg' is unreadable")]
    assert "16-bit" in problems.items[1].message and "truncated" in problems.items[2].message
    problems = Problems()  # without decoding, the header check still refuses the empty and the 16-bit one
    check_images(tmp_path, tmp_path / "captures.csv", rows, None, False, problems, progress=False)
    assert [p.row for p in problems.items] == [3, 4]


def test_siteloc_query_names_a_corrupt_image_before_loading_anything(tmp_path):
    from typer.testing import CliRunner

    from stages.app import app

    good, cut, junk = tmp_path / "good.jpg", tmp_path / "cut.jpg", tmp_path / "junk.jpg"
    Image.fromarray(noise()).save(good)
    cut.write_bytes(good.read_bytes()[:300])
    junk.write_bytes(RNG.bytes(300))
    res = CliRunner().invoke(app, ["query", str(tmp_path / "no-index"), str(good), str(cut), str(junk),
                                   "--model", str(tmp_path / "no-model.pt")])
    assert res.exit_code == 1
    assert "unexpected" not in res.output and "Traceback" not in res.output
    assert str(cut) in res.output and "truncated" in res.output
    assert str(junk) in res.output and "not an image" in res.output
    assert str(good) + ":" not in res.output
