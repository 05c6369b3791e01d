"""The unit of work of `siteloc extract`: the images it describes and the chunk files it resumes from.

Both engines (`run_extract`'s local pool and `extract_ray`'s actors) write chunk k's two tables into the
extraction's `.partial/` folder the same way, and `run_extract` merges whatever chunks are there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io import tables
from pipeline.retrieval.descriptors import ImageDescriptors


@dataclass(frozen=True)
class ImageRecord:
    image_id: str
    x: float
    y: float
    theta: float
    group: str  # the stop, or the run, the image belongs to
    split: str  # the ingest split for stops; "run:<name>" for run frames


def chunk_done(partial: Path, k: int) -> bool:
    """Chunk k's tables are both in `partial` (each is written under a temporary name, rpa last)."""
    return (partial / f"ipa-{k:05d}.parquet").is_file() and (partial / f"rpa-{k:05d}.parquet").is_file()


def write_chunk(partial: Path, k: int, image_ids: list[str], described: list[ImageDescriptors]) -> None:
    """Chunk k's ipa and rpa tables in `partial`."""
    keys = ("image_id", "region", "source", "x1", "y1", "x2", "y2", "score", "class_id")
    rpa = {key: [] for key in keys}
    for image_id, d in zip(image_ids, described, strict=True):
        for j, ((src, score, cls), box) in enumerate(zip(d.meta, d.boxes, strict=True)):
            for key, v in zip(keys, (image_id, j, src, *box.tolist(), score, cls), strict=True):
                rpa[key].append(v)
    ipa = np.stack([d.ipa for d in described])
    tables.write_table(partial / f"ipa-{k:05d}.parquet", tables.to_table("ipa", {
        "image_id": list(image_ids), "descriptor": tables.descriptor_array(ipa)}), "ipa")
    desc = np.vstack([d.rpa for d in described]) if described else np.zeros((0, ipa.shape[1]), np.float32)
    tables.write_table(partial / f"rpa-{k:05d}.parquet", tables.to_table("rpa", {
        **rpa, "descriptor": tables.descriptor_array(desc)}), "rpa")
