"""A pool of distinct wall pictures: procedural art, charts, text notices and crops of photographs.

Real floors hang different pictures in different places, and that is much of what tells one corridor
from its twin across the building. `picture(index, seed, photos)` draws picture `index` of a site from
its own random stream, so the pool is unbounded (a site takes one per poster, a changed site takes new
ones past the end) and the same index and seed always give the same bytes. Styles rotate with the index;
within a style, palette, layout and text are drawn, so no two pictures of a pool look alike.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

SIZE = (256, 192)  # (height, width) of a portrait picture; landscape ones are the transpose
WORDS = ("meeting", "quarterly", "results", "safety", "training", "seminar", "laboratory", "project", "team",
         "coffee", "recycling", "welcome", "deadline", "schedule", "floor", "report", "budget", "research",
         "visitors", "please", "keep", "closed", "thank", "lunch", "talk", "conference", "workshop", "robotics",
         "vision", "mapping", "data", "open", "day", "library", "network", "printer", "kitchen", "rules",
         "health", "first", "aid", "exam", "career", "fair", "summer", "school", "colloquium", "award", "call",
         "papers", "sensor", "navigation", "lecture", "series", "innovation", "startup", "hackathon", "choir",
         "yoga", "running", "club", "charity", "book", "swap", "bicycle", "parking", "energy", "saving")
STYLES = ("photo", "blocks", "landscape", "chart", "notice", "waves", "blobs", "rings")


@lru_cache(maxsize=16)
def font(size: int, style: str = "sans") -> ImageFont.FreeTypeFont:
    """DejaVu from matplotlib's data (a dependency), else Pillow's built-in face: both scale."""
    names = {"sans": "DejaVuSans.ttf", "bold": "DejaVuSans-Bold.ttf", "serif": "DejaVuSerif.ttf",
             "mono": "DejaVuSansMono.ttf"}
    try:
        from matplotlib import get_data_path

        return ImageFont.truetype(f"{get_data_path()}/fonts/ttf/{names[style]}", size)
    except (ImportError, OSError):
        return ImageFont.load_default(size=size)


def picture_rng(seed: int, index: int, salt: int = 0) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index), 0x9E3779B9 + salt])


def palette(rng: np.random.Generator, n: int) -> np.ndarray:
    """`n` colours (n, 3) in [0, 1] spread around the hue circle from a random start, random saturation."""
    import colorsys

    h0 = rng.random()
    sat, val = rng.uniform(0.35, 0.95), rng.uniform(0.55, 0.95)
    return np.array([colorsys.hsv_to_rgb((h0 + k / n + rng.normal(0, 0.03)) % 1.0, sat, val * rng.uniform(0.8, 1.0))
                     for k in range(n)])


def sentence(rng: np.random.Generator, n: int) -> str:
    return " ".join(WORDS[int(i)] for i in rng.integers(0, len(WORDS), n))


def picture(index: int, seed: int, photos: list[np.ndarray] | tuple = ()) -> np.ndarray:
    """Picture `index` of the pool of site `seed`, (H, W, 3) uint8; portrait or landscape, drawn."""
    rng = picture_rng(seed, index)
    style = STYLES[index % len(STYLES)]
    if style == "photo" and not photos:
        style = "blobs"
    h, w = SIZE if rng.random() < 0.6 else SIZE[::-1]
    draw = {"photo": _photo_crop, "blocks": _blocks, "landscape": _landscape, "chart": _chart, "notice": _notice,
            "waves": _waves, "blobs": _blobs, "rings": _rings}[style]
    img = draw(rng, h, w, photos) if style == "photo" else draw(rng, h, w)
    return np.asarray(img, dtype=np.uint8)


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def _caption(img: Image.Image, rng: np.random.Generator, colour=(255, 255, 255), band=(20, 20, 20)) -> Image.Image:
    """A title band at the top or the bottom with a few words."""
    d = ImageDraw.Draw(img)
    w, h = img.size
    bh = int(h * rng.uniform(0.12, 0.2))
    y0 = 0 if rng.random() < 0.5 else h - bh
    d.rectangle([0, y0, w, y0 + bh], fill=band)
    d.text((6, y0 + bh * 0.15), sentence(rng, 2).upper(), font=font(max(9, int(bh * 0.5)), "bold"), fill=colour)
    return img


def _photo_crop(rng, h, w, photos) -> Image.Image:
    """A random window of one photograph (30-80 % of its side), possibly mirrored and colour graded."""
    src = photos[int(rng.integers(0, len(photos)))]
    sh, sw = src.shape[:2]
    scale = rng.uniform(0.3, 0.8)
    ch = int(min(sh, sw * h / w) * scale)
    cw = int(ch * w / h)
    y, x = int(rng.integers(0, sh - ch + 1)), int(rng.integers(0, sw - cw + 1))
    crop = Image.fromarray(np.ascontiguousarray(src[y:y + ch, x:x + cw])).resize((w, h), Image.BILINEAR)
    a = np.asarray(crop, np.float64) / 255.0
    if rng.random() < 0.5:
        a = a[:, ::-1]
    grade = rng.choice(["none", "duotone", "warm", "cool", "grey"])
    if grade == "duotone":
        c0, c1 = palette(rng, 2)
        lum = a.mean(axis=2, keepdims=True)
        a = c0 * (1 - lum) + c1 * lum
    elif grade in ("warm", "cool"):
        a = a * (np.array([1.1, 1.0, 0.85]) if grade == "warm" else np.array([0.85, 0.95, 1.1]))
    elif grade == "grey":
        a = np.repeat(a.mean(axis=2, keepdims=True), 3, axis=2)
    img = Image.fromarray(_to_u8(a))
    return _caption(img, rng) if rng.random() < 0.5 else img


def _blocks(rng, h, w) -> Image.Image:
    """Rectangles from recursive splits (Mondrian-like), bold lines between them."""
    img = Image.new("RGB", (w, h), (245, 242, 235))
    d = ImageDraw.Draw(img)
    colours = [tuple(int(v * 255) for v in c) for c in palette(rng, 4)] + [(245, 242, 235)]
    boxes = [(0, 0, w, h)]
    for _ in range(int(rng.integers(5, 11))):
        k = int(rng.integers(0, len(boxes)))
        x0, y0, x1, y1 = boxes.pop(k)
        if (x1 - x0) > (y1 - y0):
            cut = int(x0 + (x1 - x0) * rng.uniform(0.3, 0.7))
            boxes += [(x0, y0, cut, y1), (cut, y0, x1, y1)]
        else:
            cut = int(y0 + (y1 - y0) * rng.uniform(0.3, 0.7))
            boxes += [(x0, y0, x1, cut), (x0, cut, x1, y1)]
    line = int(rng.integers(3, 8))
    for b in boxes:
        d.rectangle(b, fill=colours[int(rng.integers(0, len(colours)))], outline=(20, 20, 20), width=line)
    return img


def _landscape(rng, h, w) -> Image.Image:
    """Sky gradient, a sun or moon, three ridges of mountains in receding tones, sometimes a lake."""
    yy = np.linspace(0, 1, h)[:, None, None]
    top, horizon = palette(rng, 2)
    sky = top * (1 - yy) + (0.6 * horizon + 0.4) * yy
    a = np.broadcast_to(sky, (h, w, 3)).copy()
    xx = np.arange(w)
    sx, sy, sr = rng.uniform(0.15, 0.85) * w, rng.uniform(0.1, 0.4) * h, rng.uniform(0.05, 0.12) * w
    yg, xg = np.mgrid[0:h, 0:w]
    a[(xg - sx) ** 2 + (yg - sy) ** 2 < sr**2] = rng.uniform(0.85, 1.0, 3)
    ground = palette(rng, 3) * 0.7
    for k, base in enumerate(np.sort(rng.uniform(0.4, 0.85, 3))):
        phase, freq = rng.uniform(0, 2 * math.pi, 3), rng.uniform(1, 6, 3)
        ridge = base * h + sum(h * 0.08 / (j + 1) * np.sin(freq[j] * xx / w * 2 * math.pi + phase[j]) for j in range(3))
        a[yg > ridge[None, :]] = ground[k] * (0.6 + 0.2 * k)
    if rng.random() < 0.4:
        a[int(h * 0.85):] = a[int(h * 0.85):] * 0.5 + np.array([0.2, 0.35, 0.55]) * 0.5
    return Image.fromarray(_to_u8(a))


def _chart(rng, h, w) -> Image.Image:
    """A bar, line or pie chart with a title, axes and a legend strip."""
    img = Image.new("RGB", (w, h), (255, 255, 255))
    d = ImageDraw.Draw(img)
    colours = [tuple(int(v * 255) for v in c) for c in palette(rng, 5)]
    d.text((8, 6), sentence(rng, 2).title(), font=font(int(h * 0.07), "bold"), fill=(30, 30, 30))
    x0, y0, x1, y1 = int(w * 0.12), int(h * 0.2), int(w * 0.95), int(h * 0.88)
    kind = rng.choice(["bar", "line", "pie"])
    if kind == "pie":
        cx, cy, r = (x0 + x1) / 2, (y0 + y1) / 2, min(x1 - x0, y1 - y0) / 2
        shares = rng.dirichlet(np.ones(int(rng.integers(3, 6)))) * 360
        start = rng.uniform(0, 360)
        for k, s in enumerate(shares):
            d.pieslice([cx - r, cy - r, cx + r, cy + r], start, start + s, fill=colours[k % len(colours)],
                       outline=(255, 255, 255))
            start += s
    else:
        d.line([x0, y0, x0, y1, x1, y1], fill=(40, 40, 40), width=2)
        n = int(rng.integers(4, 11))
        walk = np.cumsum(rng.normal(0, 1.0, n))
        vals = 0.1 + 0.85 * (walk - walk.min()) / max(float(np.ptp(walk)), 1e-9)
        xs = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
        if kind == "bar":
            bw = (x1 - x0) / n * 0.7
            for k, (x, v) in enumerate(zip(xs, vals, strict=True)):
                d.rectangle([x - bw / 2, y1 - v * (y1 - y0), x + bw / 2, y1], fill=colours[k % 2])
        else:
            for series in range(int(rng.integers(1, 4))):
                v = np.clip(vals + rng.normal(0, 0.15, n) * series, 0.02, 1.0)
                pts = [(float(x), float(y1 - vv * (y1 - y0))) for x, vv in zip(xs, v, strict=True)]
                d.line(pts, fill=colours[series], width=3)
    return img


def _notice(rng, h, w) -> Image.Image:
    """A printed notice: coloured header band with a title, lines of text, sometimes a logo."""
    paper = tuple(int(v) for v in rng.uniform(235, 255, 3))
    img = Image.new("RGB", (w, h), paper)
    d = ImageDraw.Draw(img)
    head = tuple(int(v * 255) for v in palette(rng, 1)[0])
    bh = int(h * rng.uniform(0.15, 0.3))
    d.rectangle([0, 0, w, bh], fill=head)
    d.text((8, bh * 0.2), sentence(rng, 1).upper(), font=font(int(bh * 0.45), "bold"), fill=(255, 255, 255))
    size = int(h * rng.uniform(0.045, 0.07))
    y = bh + 8
    body = font(size, str(rng.choice(["sans", "serif", "mono"])))
    while y < h - size - 6:
        d.text((8, y), sentence(rng, int(rng.integers(2, 5))), font=body, fill=(40, 40, 40))
        y += int(size * rng.uniform(1.3, 1.8))
    if rng.random() < 0.5:
        r = int(w * 0.1)
        d.ellipse([w - 2 * r - 6, h - 2 * r - 6, w - 6, h - 6], fill=head)
    return img


def _waves(rng, h, w) -> Image.Image:
    """Bands of colour along random sinusoids."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    colours = palette(rng, int(rng.integers(3, 7)))
    a0, f0, f1 = rng.uniform(0, math.pi), rng.uniform(1, 4), rng.uniform(2, 9)
    t = (xx * math.cos(a0) + yy * math.sin(a0) + 0.08 * np.sin(f1 * 2 * math.pi * (xx - yy))) * f0
    band = np.floor(t * len(colours)).astype(int) % len(colours)
    return Image.fromarray(_to_u8(colours[band]))


def _blobs(rng, h, w) -> Image.Image:
    """A two-colour gradient with random discs over it."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    c0, c1, c2 = palette(rng, 3)
    ang = rng.uniform(0, 2 * math.pi)
    t = ((xx * math.cos(ang) + yy * math.sin(ang)) % 1.0)[..., None]
    a = c0 * (1 - t) + c1 * t
    for _ in range(int(rng.integers(3, 12))):
        cx, cy, r = rng.uniform(0, w / max(h, w)), rng.uniform(0, h / max(h, w)), rng.uniform(0.04, 0.25)
        a[(xx - cx) ** 2 + (yy - cy) ** 2 < r**2] = c2 * rng.uniform(0.4, 1.0)
    return Image.fromarray(_to_u8(a))


def _rings(rng, h, w) -> Image.Image:
    """Concentric rings around one or two centres, in a random palette."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    colours = palette(rng, int(rng.integers(2, 6)))
    d = np.full((h, w), np.inf)
    for _ in range(int(rng.integers(1, 3))):
        cx, cy = rng.uniform(0, 1), rng.uniform(0, 1)
        d = np.minimum(d, np.hypot(xx - cx, yy - cy))
    band = np.floor(d * rng.uniform(8, 20)).astype(int) % len(colours)
    return Image.fromarray(_to_u8(colours[band]))
