"""The unit of work of `siteloc extract`: the images it describes and the chunk files it resumes from.

Both engines (`run_extract`'s local pool and `extract_ray`'s actors) write chunk k's two tables into the
extraction's `.partial/` folder the same way, and `run_extract` merges whatever chunks are there. Before a
rerun resumes, `discard_damaged_chunks` reads every finished chunk in full and deletes (with a warning) any
that does not hold its images' rows, so that a truncated or overwritten file is computed again.
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


def chunk_files(partial: Path, k: int) -> list[Path]:
    return [partial / f"ipa-{k:05d}.parquet", partial / f"rpa-{k:05d}.parquet"]


def check_chunk(partial: Path, k: int, image_ids: list[str]) -> bool:
    """Read chunk k's tables in full; ValueError (or the reader's InputError) unless they are `ipa` and `rpa`
    tables of the current schema whose ipa rows are `image_ids` in order and whose regions are of those images."""
    ipa_path, rpa_path = chunk_files(partial, k)
    ipa = tables.read_table(ipa_path, "ipa")
    found = ipa.column("image_id").to_pylist()
    if found != list(image_ids):
        raise ValueError(f"{len(found)} ipa rows, not the chunk's {len(image_ids)} images in order")
    strays = set(tables.read_table(rpa_path, "rpa").column("image_id").to_pylist()) - set(image_ids)
    if strays:
        raise ValueError(f"regions of {len(strays)} images outside the chunk")
    return True


def discard_damaged_chunks(partial: Path, chunks: list[list[ImageRecord]]) -> list[int]:
    """Delete every finished chunk of `partial` that `check_chunk` refuses (a warning names it); returns them."""
    from functools import partial as bind

    from pipeline.chunked_encoding import checked_chunk, remove_entry

    damaged = []
    for k, chunk in enumerate(chunks):
        files = chunk_files(partial, k)
        present = [f.exists() or f.is_symlink() for f in files]
        if all(present):
            if checked_chunk(files, bind(check_chunk, partial, k, [rec.image_id for rec in chunk])) is None:
                damaged.append(k)
        elif any(present):  # interrupted between its two tables: unfinished, not damaged
            for f in files:
                remove_entry(f)
    return damaged


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
