"""Every image siteloc reads is decoded here, from a file or from bytes (a ROS bag message).

What cannot be decoded faithfully to 8-bit pixels is refused with an `ImageError` (an `InputError`) that names
the file or message and says how to fix it: an empty file, data PIL cannot identify, a truncated or damaged
image, more than `MAX_PIXELS` pixels (a decompression bomb), and 16-bit, 32-bit or float pixels, which a
conversion to RGB would clip. PIL's `ImageFile.LOAD_TRUNCATED_IMAGES` must stay False: truncation is found
by decoding the whole image.
"""

from __future__ import annotations

import contextlib
import io
import re
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.errors import InputError, Problem, excerpt

if TYPE_CHECKING:  # PIL is imported on first use: modules that only catch ImageError keep the CLI's start light
    from PIL import Image

# PIL's own default limit (a 9459 x 9459 image): far above a camera frame or a map, far below what exhausts
# memory. PIL itself only warns between this and twice it; here anything above it is refused.
MAX_PIXELS = 89_478_485

_REEXPORT = "export or copy the image again as JPEG or PNG"
_MAGIC = {"PNG": b"\x89PNG\r\n\x1a\n", "JPEG": b"\xff\xd8\xff"}
# warnings.catch_warnings swaps the process-wide filter list; concurrent callers (threads describing frames)
# would otherwise restore each other's copy and leave the filter changed for other code.
_WARNINGS = threading.Lock()

Source = str | Path | bytes | bytearray | memoryview


class ImageError(InputError):
    """An image that cannot be decoded faithfully; `name` is its file (or message), `message` and `fix` say why."""

    def __init__(self, name: str, message: str, fix: str):
        self.name, self.message, self.fix = name, message, fix
        super().__init__(f"cannot read the image {name}", [Problem(name, message, fix=fix)])

    def __reduce__(self):  # the default pickles the rendered text alone; replay processes send these back
        return type(self), (self.name, self.message, self.fix)


def image_size(source: Source, *, name: str | None = None, max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """(width, height) of an image, from its header only: empty, unidentifiable, too large and 16-bit or float
    images are refused, a truncated one is not (that takes `open_image`)."""
    with _open(source, name, max_pixels) as (im, _):
        return im.size


def open_image(source: Source, *, name: str | None = None, rgb: bool = True,
               max_pixels: int = MAX_PIXELS) -> Image.Image:
    """The fully decoded image at `source` (a path, or bytes named `name`), as RGB, or with `rgb=False` in its
    own 8-bit mode (L, LA, P, RGBA, ...). Palette, grey, alpha and CMYK images convert as `Image.convert` does."""
    from PIL import Image

    with _open(source, name, max_pixels) as (im, label):
        try:
            im.load()
        except Image.DecompressionBombError as exc:  # a GIF frame, for one, can be larger than the image
            raise _bomb(label, im.size, max_pixels, exc) from None
        except Exception as exc:  # noqa: BLE001 - decoders of damaged data raise OSError, SyntaxError, EOFError...
            if isinstance(exc, EOFError) or "truncated" in str(exc).lower():
                raise ImageError(label, f"truncated image: its data ends early ({excerpt(exc)})",
                                 "the file is cut short (an interrupted copy or download?): copy it again") from None
            raise ImageError(label, f"damaged image data ({type(exc).__name__}: {excerpt(exc)})", _REEXPORT) from None
        if not rgb:
            return im.copy()
        try:
            return im.convert("RGB")
        except ValueError as exc:  # a mode PIL has no conversion for, e.g. LAB
            raise ImageError(label, f"{im.mode} image that cannot be converted to RGB ({excerpt(exc)})",
                             "convert it to 8-bit RGB") from None


def image_rgb(source: Source, *, name: str | None = None, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """`open_image` as an (H, W, 3) uint8 array."""
    return np.asarray(open_image(source, name=name, max_pixels=max_pixels))


@contextlib.contextmanager
def _open(source: Source, name: str | None, max_pixels: int) -> Iterator[tuple[Image.Image, str]]:
    """(the opened, not yet decoded image, its label), identified and checked; closed on exit."""
    from PIL import Image, ImageMode, UnidentifiedImageError

    label = name if name is not None else (str(source) if isinstance(source, str | Path) else "image data")
    if isinstance(source, str | Path):
        try:
            with open(source, "rb") as fh:
                head = fh.read(16)
        except OSError as exc:
            raise ImageError(label, f"cannot be read ({exc.strerror or type(exc).__name__})",
                             "check that the file exists and is readable") from None
        fp = Path(source)
    else:
        head = bytes(source[:16])
        fp = io.BytesIO(bytes(source))
    if not head:
        raise ImageError(label, "empty file (0 bytes)", _REEXPORT)
    try:
        with _WARNINGS, warnings.catch_warnings():
            # Above max_pixels the image is refused below; PIL's warning would only add noise first.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(fp)
    except Image.DecompressionBombError as exc:
        raise _bomb(label, None, max_pixels, exc) from None
    except Exception as exc:  # noqa: BLE001 - plugins raise SyntaxError, ValueError, struct.error on bad headers
        known = next((fmt for fmt, magic in _MAGIC.items() if head.startswith(magic)), None)
        if known:  # PIL says no more than "cannot identify" or "Truncated File Read" for a header cut short
            raise ImageError(label, f"{known} file truncated or damaged in its header", _REEXPORT) from None
        if isinstance(exc, UnidentifiedImageError):
            raise ImageError(label, f"not an image PIL can identify (it begins with {excerpt(repr(head))})",
                             _REEXPORT) from None
        raise ImageError(label, f"damaged image header ({type(exc).__name__}: {excerpt(exc)})", _REEXPORT) from None
    with im:
        if im.width * im.height > max_pixels:
            raise _bomb(label, im.size, max_pixels, None)
        typestr = ImageMode.getmode(im.mode).typestr
        if typestr not in ("|u1", "|b1"):  # 16-bit, 32-bit or float samples: RGB would clip them at 255
            what = ("16-bit grayscale image" if typestr[1:] == "u2" else "floating-point image" if typestr[1] == "f"
                    else "image of more than 8 bits per sample (a 16- or 32-bit PGM or TIFF)")
            raise ImageError(label, f"{what}, PIL mode {im.mode}: siteloc reads 8-bit images and converting it to "
                             f"RGB would clip its values",
                             "convert it to 8-bit, e.g. `convert IN -depth 8 OUT.png` (ImageMagick)")
        yield im, label


def _bomb(label: str, size: tuple[int, int] | None, max_pixels: int, exc: Exception | None) -> ImageError:
    if size is not None:
        what = f"{size[0]} x {size[1]} = {size[0] * size[1]:,} pixels"
    else:  # PIL refused it before saying its size: "Image size (N pixels) exceeds limit of ..."
        found = re.search(r"\((\d+) pixels\)", str(exc))
        what = f"{int(found[1]):,} pixels" if found else "more pixels than PIL accepts"
    return ImageError(label, f"image too large ({what}): more than {max_pixels:,} pixels is refused as a possible "
                      f"decompression bomb", f"downscale it to at most {max_pixels:,} pixels")
