"""The geo-tagged images `train-place` learns from, and which of them are positives and negatives.

Training images: the database views (the ingest's `train` stops) and every `frame_stride`-th frame of
the mapping runs that has a ground-truth pose. One mapping run can be held out as validation: its frames
are then queries against the database views, as `evaluate-retrieval` asks its queries. Test stops and
query runs are never read. Two images are positives when within `positive_m` and `positive_heading_deg`
of each other and taken from different groups (stops, runs: a run's neighbouring frames are nearly the
same picture and teach nothing); negatives lie beyond `negative_m` or `negative_heading_deg`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem


@dataclass
class PlaceImages:
    paths: list[Path]  # image files
    ids: list[str]  # image_id, relative to the ingest
    poses: np.ndarray  # (N, 3) x, y, theta (radians), ground truth
    group: np.ndarray  # (N,) stop id or run name
    database: np.ndarray  # (N,) bool: a database view (a train stop's)
    validation: np.ndarray  # (N,) bool: a frame of the held-out mapping run (never trained on)

    def __len__(self) -> int:
        return len(self.paths)


def heading_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| wrapped to [0, pi]."""
    return np.abs(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b)))))


def place_images(data: Path, *, frame_stride: int, validation_run: str | None) -> PlaceImages:
    """The training and validation images of an ingested site."""
    from pipeline.io import tables

    data = Path(data)
    images = tables.read_table(data / "images.parquet", "images").to_pydict()
    ids, poses, group, database = [], [], [], []
    for i, split in enumerate(images["split"]):
        if split == "train":
            ids.append(images["image_id"][i])
            poses.append((images["x"][i], images["y"][i], images["theta"][i]))
            group.append(images["stop_id"][i])
            database.append(True)
    run_files = sorted((data / "runs").glob("mapping*.parquet")) if (data / "runs").is_dir() else []
    runs = [p.stem for p in run_files]
    held = None
    if validation_run is not None and runs:
        held = runs[-1] if validation_run == "last" else validation_run
        if held not in runs:
            raise InputError(f"{data}: place.validation_run '{validation_run}' is not a mapping run",
                             [Problem(str(data / "runs"), f"mapping runs: {runs}",
                                      fix="name one of them, 'last', or null to hold none out")])
        if len(runs) == 1 and validation_run == "last":
            held = None  # the only mapping run trains, unless named
    validation = [False] * len(ids)
    for path in run_files:
        t = tables.read_table(path, "runs").select(["image_id", "gt_x", "gt_y", "gt_theta"]).to_pydict()
        keep = [k for k, im in enumerate(t["image_id"]) if im is not None and t["gt_x"][k] is not None]
        for k in keep[::frame_stride]:
            ids.append(t["image_id"][k])
            poses.append((t["gt_x"][k], t["gt_y"][k], t["gt_theta"][k]))
            group.append(path.stem)
            database.append(False)
            validation.append(path.stem == held)
    if not any(database):
        raise InputError(f"{data}: no database views to train a place network on", [Problem(
            str(data / "images.parquet"), "no image of split 'train'", fix="ingest a site with train stops")])
    return PlaceImages([data / i for i in ids], ids, np.asarray(poses, dtype=np.float64), np.asarray(group),
                       np.asarray(database), np.asarray(validation, dtype=bool))


@dataclass
class PairSets:
    positives: list[np.ndarray]  # per anchor: positive image indices
    negatives: list[np.ndarray]  # per anchor: negative image indices
    anchors: np.ndarray  # image indices with at least one positive and enough negatives


def pair_sets(poses: np.ndarray, group: np.ndarray, *, positive_m: float, positive_heading_deg: float,
              negative_m: float, negative_heading_deg: float, min_negatives: int) -> PairSets:
    """Positive and negative images of every image of a (training) set, from its poses."""
    d = np.linalg.norm(poses[:, None, :2] - poses[None, :, :2], axis=2)
    dth = heading_gap(poses[:, None, 2], poses[None, :, 2])
    pos = (d <= positive_m) & (dth <= np.radians(positive_heading_deg)) & (group[:, None] != group[None, :])
    neg = (d > negative_m) | (dth > np.radians(negative_heading_deg))
    positives = [np.flatnonzero(row) for row in pos]
    negatives = [np.flatnonzero(row) for row in neg]
    anchors = np.asarray([i for i in range(len(poses)) if len(positives[i]) and len(negatives[i]) >= min_negatives],
                         dtype=np.int64)
    return PairSets(positives, negatives, anchors)


def mine(sim: np.ndarray, pairs: PairSets, anchors: np.ndarray, *, negatives: int, hard_pool: int,
         rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(positive (A,), negatives (A, n)) of each anchor from the current similarities `sim` (N, N): the most
    similar positive (NetVLAD's weak supervision picks the best-matching one) and `negatives` drawn from
    the `hard_pool` most similar negatives."""
    pos = np.empty(len(anchors), dtype=np.int64)
    neg = np.empty((len(anchors), negatives), dtype=np.int64)
    for k, a in enumerate(anchors):
        p = pairs.positives[a]
        pos[k] = p[np.argmax(sim[a, p])]
        n = pairs.negatives[a]
        pool = n[np.argsort(-sim[a, n], kind="stable")[:hard_pool]]
        neg[k] = rng.choice(pool, size=negatives, replace=False)
    return pos, neg
