"""COCO object boxes (`annotations.json`) of a capture directory.

Images are matched by `file_name`, which must be the image's path relative to the site root as in
captures.csv. Category names must be classes of site.yaml; the detector label of a class is its
1-based index in `classes` (0 is background). COCO `bbox` is [x, y, width, height] in pixels.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import InputError, Problems, excerpt
from pipeline.io.site import Site
from pipeline.io.text_files import read_text


@dataclass(frozen=True)
class Box:
    image_id: str
    class_id: int
    class_name: str
    x1: float
    y1: float
    x2: float
    y2: float


def read_coco_boxes(
    path: Path,
    site: Site | None,
    sizes: dict[str, tuple[int, int, str]],
    known_images: set[str],
    min_side: float,
    problems: Problems,
) -> list[Box]:
    """Validate and convert COCO annotations; each bad annotation is reported by its index and id."""
    try:
        doc = json.loads(read_text(path, what="annotation file"))
    except InputError as exc:
        problems.extend(exc.problems)
        return []
    except json.JSONDecodeError as exc:
        problems.add(path, f"not valid JSON: {excerpt(exc, 120)}", fix="export the annotations as COCO JSON")
        return []
    if not isinstance(doc, dict) or not all(
        isinstance(doc.get(k), list) for k in ("images", "annotations", "categories")
    ):
        problems.add(path, "a COCO file needs lists 'images', 'annotations' and 'categories'")
        return []

    categories: dict[int, str] = {}
    for i, cat in enumerate(doc["categories"]):
        if not isinstance(cat, dict) or "id" not in cat or "name" not in cat:
            problems.add(path, f"categories[{i}] needs 'id' and 'name'")
            continue
        categories[cat["id"]] = cat["name"]
        if site is not None and cat["name"] not in site.classes:
            problems.add(
                path,
                f"category '{cat['name']}' (id {cat['id']}) is not a class of site.yaml ({', '.join(site.classes)})",
                key=f"categories[{i}]",
                fix="rename the category or add the class to site.yaml classes",
            )

    images: dict[int, str] = {}
    for i, im in enumerate(doc["images"]):
        if not isinstance(im, dict) or "id" not in im or "file_name" not in im:
            problems.add(path, f"images[{i}] needs 'id' and 'file_name'")
            continue
        images[im["id"]] = im["file_name"]
        if im["file_name"] not in known_images:
            problems.add(
                path,
                f"images[{i}] file_name '{im['file_name']}' is not in captures.csv",
                key=f"images[{i}]",
                fix="file_name must be the image path relative to the site root, as in captures.csv",
            )

    boxes: list[Box] = []
    for i, ann in enumerate(doc["annotations"]):
        where = f"annotations[{i}]"
        if not isinstance(ann, dict) or not {"image_id", "category_id", "bbox"} <= set(ann):
            problems.add(path, f"{where} needs 'image_id', 'category_id' and 'bbox'", key=where)
            continue
        where += f" (id {ann.get('id', '?')})"
        name = categories.get(ann["category_id"])
        file_name = images.get(ann["image_id"])
        if name is None:
            problems.add(path, f"{where} has unknown category_id {ann['category_id']}", key=where)
        if file_name is None:
            problems.add(path, f"{where} refers to image_id {ann['image_id']}, which is not in 'images'", key=where)
        bbox = ann["bbox"]
        if not (
            isinstance(bbox, list)
            and len(bbox) == 4
            and all(isinstance(v, int | float) and math.isfinite(v) for v in bbox)
        ):
            problems.add(path, f"{where} bbox must be [x, y, width, height] numbers, got {bbox!r}", key=where)
            continue
        x, y, w, h = (float(v) for v in bbox)
        if w < min_side or h < min_side:
            problems.add(
                path,
                f"{where} box {w:.1f}x{h:.1f} px is smaller than {min_side} px",
                key=where,
                fix="drop degenerate boxes",
            )
            continue
        if file_name is None or name is None:
            continue
        if file_name in sizes:
            width, height, _ = sizes[file_name]
            # Half a pixel of slack: COCO tools round box edges to pixel centres.
            if x < -0.5 or y < -0.5 or x + w > width + 0.5 or y + h > height + 0.5:
                problems.add(
                    path,
                    f"{where} box [{x:.1f}, {y:.1f}, {x + w:.1f}, {y + h:.1f}] leaves the "
                    f"{width}x{height} image '{file_name}'",
                    key=where,
                    fix="clip the box to the image",
                )
                continue
        if site is not None and name in site.classes:
            boxes.append(Box(file_name, site.class_id(name), name, x, y, x + w, y + h))
    return boxes
