"""Textures of the signage a real floor carries: room plates, notice boards, escape plans, wing signs.

Each is drawn with PIL from what the scene says (a plate's number and name, where an escape plan hangs,
which rooms a sign points to), so it is both distinctive and true to the floor: an escape plan shows this
floor's walls and a red dot where it hangs. Random parts (a board's notes) come from a stream of the
site seed and the object's own key, so the same scene always gives the same bytes.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
from PIL import Image, ImageDraw

from pipeline.sitegen.pictures import font, palette, sentence

PLATE_PX = (80, 128)  # (height, width)
BOARD_PX = (192, 256)
PLAN_PX = (192, 256)
SIGN_PX = (64, 256)


def key_rng(seed: int, key: str) -> np.random.Generator:
    digest = hashlib.sha256(f"{int(seed)}|{key}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def _rgb255(colour) -> tuple[int, int, int]:
    return tuple(int(np.clip(c, 0, 1) * 255 + 0.5) for c in colour)  # type: ignore[return-value]


def plate_image(number: str, name: str, colour) -> np.ndarray:
    """A door plate: the wing's colour as a band on the left, the number in bold, an optional name."""
    h, w = PLATE_PX
    img = Image.new("RGB", (w, h), (238, 238, 232))
    d = ImageDraw.Draw(img)
    d.rectangle([0, 0, 18, h], fill=_rgb255(colour))
    size = 34 if not name else 30
    d.text((24, 4 if name else 18), number, font=font(size, "bold"), fill=(25, 25, 25))
    if name:
        words = name.split()
        lines = [" ".join(words[:2]), " ".join(words[2:])] if len(name) > 14 else [name]
        for k, line in enumerate(lines):
            d.text((24, 40 + 17 * k), line, font=font(14, "sans"), fill=(60, 60, 60))
    d.rectangle([0, 0, w - 1, h - 1], outline=(120, 120, 120), width=2)
    return np.asarray(img)


def board_image(seed: int, key: str) -> np.ndarray:
    """A cork notice board with 3-7 pinned notes; `key` (which board, which version) seeds the notes."""
    rng = key_rng(seed, key)
    h, w = BOARD_PX
    cork = np.array([0.72, 0.55, 0.36]) * (0.9 + 0.1 * rng.random((h, w, 1)))
    img = Image.fromarray((np.clip(cork, 0, 1) * 255).astype(np.uint8))
    d = ImageDraw.Draw(img)
    for _ in range(int(rng.integers(3, 8))):
        nw, nh = int(rng.uniform(0.22, 0.42) * w), int(rng.uniform(0.25, 0.5) * h)
        x, y = int(rng.integers(6, w - nw - 5)), int(rng.integers(6, h - nh - 5))
        paper = _rgb255(palette(rng, 1)[0] * 0.35 + 0.65) if rng.random() < 0.6 else (250, 250, 246)
        d.rectangle([x, y, x + nw, y + nh], fill=paper, outline=(90, 80, 60))
        d.text((x + 4, y + 3), sentence(rng, 1).upper(), font=font(11, "bold"), fill=(30, 30, 30))
        for k in range(int((nh - 18) / 10)):
            d.line([x + 4, y + 20 + 10 * k, x + 4 + rng.uniform(0.4, 0.95) * (nw - 8), y + 20 + 10 * k],
                   fill=(110, 110, 110), width=2)
        d.ellipse([x + nw / 2 - 3, y - 2, x + nw / 2 + 3, y + 4], fill=_rgb255(palette(rng, 1)[0]))  # the pin
    d.rectangle([0, 0, w - 1, h - 1], outline=(150, 110, 60), width=6)
    return np.asarray(img)


def plan_image(scene, here: tuple[float, float], heading: float) -> np.ndarray:
    """A fire-escape plan of the floor: walls, exits in green, a red 'you are here' dot and arrow."""
    h, w = PLAN_PX
    img = Image.new("RGB", (w, h), (255, 255, 255))
    d = ImageDraw.Draw(img)
    d.rectangle([0, 0, w, 24], fill=(0, 140, 76))
    d.text((6, 3), "ESCAPE PLAN", font=font(16, "bold"), fill=(255, 255, 255))
    b = scene.bounds
    scale = min((w - 16) / b.w, (h - 36) / b.h)
    ox, oy = (w - b.w * scale) / 2, 28 + (h - 32 - b.h * scale) / 2

    def px(x: float, y: float) -> tuple[float, float]:
        return ox + (x - b.x0) * scale, oy + (b.y1 - y) * scale  # north up

    for wall in scene.walls:
        d.line([px(wall.x0, wall.y0), px(wall.x1, wall.y1)], fill=(40, 40, 40), width=1)
        dx, dy = wall.direction
        for o in wall.openings:
            if o.kind == "door" and wall.exterior:
                a = (o.start + o.end) / 2
                cx, cy = px(wall.x0 + dx * a, wall.y0 + dy * a)
                d.rectangle([cx - 3, cy - 3, cx + 3, cy + 3], fill=(0, 170, 80))
    hx, hy = px(*here)
    d.ellipse([hx - 5, hy - 5, hx + 5, hy + 5], fill=(220, 20, 20))
    d.line([hx, hy, hx + 12 * math.cos(heading), hy - 12 * math.sin(heading)], fill=(220, 20, 20), width=2)
    d.rectangle([0, 0, w - 1, h - 1], outline=(0, 140, 76), width=3)
    return np.asarray(img)


def sign_image(lines: list[tuple[str, str]], colour) -> np.ndarray:
    """A directional sign: (text, arrow) lines, arrow one of "<", ">", "^", "", on the wing's colour."""
    h, w = SIGN_PX
    img = Image.new("RGB", (w, h), _rgb255(np.asarray(colour) * 0.75))
    d = ImageDraw.Draw(img)
    size = max(12, int((h - 8) / max(1, len(lines))) - 4)
    for k, (text, arrow) in enumerate(lines):
        y = 4 + k * (size + 4)
        glyph = {"<": "\u2190", ">": "\u2192", "^": "\u2191"}.get(arrow, "")
        label = f"{glyph} {text}" if arrow == "<" else f"{text} {glyph}".strip()
        d.text((8, y), label, font=font(size, "bold"), fill=(255, 255, 255))
    return np.asarray(img)


def outside_view(facade: int, seed: int, width_px: int = 1024, height_px: int = 256) -> np.ndarray:
    """What one facade's windows look out on: sky, a street of buildings or a park, tiling along x."""
    rng = key_rng(seed, f"outside:{facade}")
    h, w = height_px, width_px
    yy = np.linspace(0, 1, h)[:, None, None]
    sky_top = np.array([0.35, 0.55, 0.85]) * rng.uniform(0.8, 1.1)
    a = np.broadcast_to(sky_top * (1 - yy) + np.array([0.85, 0.9, 0.95]) * yy, (h, w, 3)).copy()
    kind = ("buildings", "trees", "buildings", "courtyard")[facade % 4]
    x = 0
    while x < w:  # buildings or trees side by side, wrapping seamlessly (the last one is cut at w)
        bw = int(rng.integers(60, 200))
        top = int(h * rng.uniform(0.05, 0.5))
        if kind in ("buildings", "courtyard"):
            colour = palette(rng, 1)[0] * 0.5 + 0.3
            a[top:, x:x + bw] = colour
            for wy in range(top + 8, h - 10, 22):
                for wx in range(x + 6, min(x + bw, w) - 10, 18):
                    a[wy:wy + 12, wx:wx + 10] = (0.2, 0.25, 0.3) if rng.random() < 0.7 else (0.95, 0.9, 0.6)
        else:
            green = np.array([0.15, 0.4, 0.15]) * rng.uniform(0.7, 1.3)
            cy, r = top + bw * 0.4, bw * 0.55
            part = a[:, x:min(x + bw, w)]  # a view: assigning through the mask paints `a`
            yg, xg = np.mgrid[0:h, 0:part.shape[1]]
            part[((xg - bw / 2) ** 2 + (yg - cy) ** 2) < r**2] = green
            a[int(cy):, x + bw // 2 - 4:x + bw // 2 + 4] = (0.3, 0.2, 0.1)
        x += bw + int(rng.integers(0, 30))
    a[int(h * 0.92):] = (0.4, 0.4, 0.38)  # the ground
    return (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
