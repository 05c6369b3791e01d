"""Detection samples from an ingested site (`images.parquet` + `boxes.parquet`), split by whole stops.

Train and validation come from the ingest's `train` split, divided again by stop (seeded), so views of
one place never sit on both sides; the ingest's `test` stops stay untouched for evaluation. Images are
loaded with PIL and scaled to `max_side` (longest side) when asked; boxes are scaled with them and
`to_original` maps predictions back to the image's own pixels. Training augmentation: horizontal flips
(boxes mirrored) and colour jitter (torchvision), both drawn from a seeded generator.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.io import tables


@dataclass(frozen=True)
class Sample:
    image_id: str
    path: Path
    stop_id: str
    width: int
    height: int
    boxes: np.ndarray  # (K, 4) float32 x1, y1, x2, y2 in original pixels
    labels: np.ndarray  # (K,) int64, 1-based class ids (0 = background)


def load_samples(ingested: Path) -> tuple[list[Sample], dict[str, list[Sample]], list[str]]:
    """(all samples, {split: samples} by the ingest's split, class names) of an ingested site."""
    ingested = Path(ingested)
    images = tables.read_table(ingested / "images.parquet", "images").to_pydict()
    boxes_table = tables.read_table(ingested / "boxes.parquet", "boxes")
    meta = tables.table_metadata(boxes_table)
    classes = json.loads(meta.get("classes", "[]"))
    if not classes:
        raise InputError(f"{ingested / 'boxes.parquet'}: no class list in its metadata",
                         [Problem(str(ingested / "boxes.parquet"), "metadata siteloc.classes is missing",
                                  fix="re-run `siteloc ingest` with this version")])
    b = boxes_table.to_pydict()
    by_image: dict[str, list[int]] = {}
    for i, image_id in enumerate(b["image_id"]):
        by_image.setdefault(image_id, []).append(i)
    samples, splits = [], {}
    for k, image_id in enumerate(images["image_id"]):
        idx = by_image.get(image_id, [])
        box = np.array([[b["x1"][i], b["y1"][i], b["x2"][i], b["y2"][i]] for i in idx], dtype=np.float32).reshape(-1, 4)
        s = Sample(image_id, ingested / image_id, images["stop_id"][k], int(images["width"][k]),
                   int(images["height"][k]), box, np.array([b["class_id"][i] for i in idx], dtype=np.int64))
        samples.append(s)
        splits.setdefault(images["split"][k], []).append(s)
    return samples, splits, classes


def split_by_stop(samples: list[Sample], val_fraction: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """(train, val): a seeded share of whole stops goes to validation (at least one when possible)."""
    stops = sorted({s.stop_id for s in samples})
    rng = np.random.default_rng(seed)
    n_val = min(len(stops) - 1, max(1, round(val_fraction * len(stops)))) if len(stops) > 1 else 0
    val_stops = set(rng.permutation(stops)[:n_val].tolist())
    return [s for s in samples if s.stop_id not in val_stops], [s for s in samples if s.stop_id in val_stops]


def repeat_factors(samples: list[Sample], threshold: float) -> np.ndarray:
    """Repeat-factor sampling weights (Gupta et al., LVIS, 2019): rare classes are drawn more often.

    With f_c the share of images holding class c, an image's factor is max over its classes of
    max(1, sqrt(threshold / f_c)); 0 turns it off (every image 1).
    """
    factors = np.ones(len(samples))
    if threshold <= 0 or not samples:
        return factors
    classes = sorted({int(c) for s in samples for c in s.labels})
    share = {c: np.mean([c in set(s.labels.tolist()) for s in samples]) for c in classes}
    for i, s in enumerate(samples):
        for c in set(s.labels.tolist()):
            factors[i] = max(factors[i], np.sqrt(threshold / share[int(c)]))
    return factors


def scale_for(width: int, height: int, max_side: int | None) -> float:
    return 1.0 if not max_side else min(1.0, max_side / max(width, height))


def to_original(boxes: np.ndarray, scale: float) -> np.ndarray:
    """Boxes predicted on an image scaled by `scale`, in the original image's pixels."""
    return np.asarray(boxes, dtype=np.float32) / scale


class DetectionDataset:
    """A torch-style dataset: (image tensor (3, H, W) in [0, 1], target dict), optional augmentation."""

    def __init__(self, samples: list[Sample], *, max_side: int | None = None, augment: bool = False, seed: int = 0):
        self.samples, self.max_side, self.augment = samples, max_side, augment
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int):
        import torch
        from PIL import Image
        from torchvision.transforms import ColorJitter
        from torchvision.transforms.functional import pil_to_tensor

        from pipeline.io.images import open_image

        s = self.samples[i]
        img = open_image(s.path)
        scale = scale_for(s.width, s.height, self.max_side)
        if scale != 1.0:
            img = img.resize((round(s.width * scale), round(s.height * scale)), Image.BILINEAR)
        boxes = s.boxes * scale
        if self.augment:
            if self.rng.random() < 0.5:
                img = img.transpose(Image.FLIP_LEFT_RIGHT)
                w = img.width
                boxes = boxes[:, [2, 1, 0, 3]] * [-1, 1, -1, 1] + [w, 0, w, 0]
            torch.manual_seed(int(self.rng.integers(0, 2**31)))  # ColorJitter draws from torch's generator
            img = ColorJitter(brightness=0.3, contrast=0.3, saturation=0.3, hue=0.02)(img)
        image = pil_to_tensor(img).float() / 255.0
        target = {"boxes": torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 4),
                  "labels": torch.as_tensor(s.labels, dtype=torch.int64), "scale": scale}
        return image, target
