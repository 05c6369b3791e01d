"""How well a bundle's retrieval and detector do on a set of geo-tagged images, per room / area.

One measure serves three callers: `export` runs it on the ingest's held-out (test) stops and ships the
figures as the bundle's baseline (evaluation/baseline.json); `check` runs it on new captures of the
building as it is now; `diff --data` runs it for two bundles on the same images. Each image is described
by the bundle's own ONNX graph (no torch) and retrieved as the robot would (IPA Top-N, RPA re-ranking).
Per area: recall@1 / @4 (a result within `check.position_m` and `check.heading_deg` of the image's pose),
the median same-place similarity (cosine of the whitened IPA with a database view within
`check.same_place_m` and `check.same_place_deg`: 1 for an identical view) and, given a floor, how many
same-place views fall under it (changed views: a few posters change a few views, not the median), the median neighbour
similarity (the same with the nearest database view, for images that have none at their place: how
alike two neighbouring stops look) and, where the images have boxes, the COCO mAP@0.5 of the detections the
bundle keeps (score >= retrieval.rpa_min_score).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

BASELINE_FILE = "evaluation/baseline.json"
MEASURE_VERSION = 1


@dataclass
class BundleRetriever:
    """The parts of a bundle that describe and retrieve an image: describer graph, database, settings."""

    describer: object  # pipeline.runtime.describer.OnnxDescriber
    database: object  # pipeline.retrieval.database.RetrievalDatabase
    retrieval: dict  # filter.yaml's retrieval section

    @classmethod
    def from_dir(cls, root: Path, retrieval: dict | None = None) -> BundleRetriever:
        from pipeline.retrieval.database import load_database
        from pipeline.runtime.describer import OnnxDescriber

        root = Path(root)
        if retrieval is None:
            from pipeline.runtime.bundle import read_settings

            retrieval = read_settings(root)["retrieval"]
        return cls(OnnxDescriber(root / "models" / "describer.onnx", root / "models" / "describer.json",
                                 threads=None), load_database(root / "db"), retrieval)


def image_keys(images: pa.Table, bundle_images: pa.Table, proximity_m: float) -> list[str]:
    """Each image's area key: its own labels, else the area of the nearest bundle stop within
    `proximity_m`, else its own stop (`stop:<id>`)."""
    from pipeline.update.areas import area_key, stops_of

    ref = stops_of(bundle_images)
    ref_keys = ref.keys()
    cols = images.select(["stop_id", "x", "y", "room", "area"]).to_pydict()
    out = []
    for sid, x, y, room, area in zip(*cols.values(), strict=True):
        if room or not ref_keys:
            out.append(area_key(room, area, sid))
            continue
        d = np.hypot(ref.xy[:, 0] - x, ref.xy[:, 1] - y)
        j = int(np.argmin(d))
        out.append(ref_keys[j] if d[j] <= proximity_m else area_key(None, None, sid))
    return out


def _boxes_by_image(boxes: pa.Table) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    cols = boxes.select(["image_id", "class_id", "x1", "y1", "x2", "y2"]).to_pydict()
    out: dict[str, list] = {}
    for iid, c, *b in zip(*cols.values(), strict=True):
        out.setdefault(iid, []).append((c, b))
    return {k: (np.array([b for _, b in v], np.float64).reshape(-1, 4), np.array([c for c, _ in v], np.int64))
            for k, v in out.items()}


def measure(retriever: BundleRetriever, root: Path, images: pa.Table, boxes: pa.Table | None, keys: list[str], *,
            check, classes: list[str], changed_below: float | None = None, progress: bool = True) -> dict:
    """{"areas": {key: figures}, "all": figures} of the images (rows of an `images` table under `root`);
    with `changed_below`, the figures count the same-place views less similar than it (`same_place_changed`)."""
    from pipeline.detection.evaluate import coco_map
    from pipeline.progress import progress_bar
    from pipeline.retrieval.database import query_database
    from pipeline.retrieval.metrics import positives

    position_m, heading_deg = check.position_m, check.heading_deg
    r, rdb = retriever.retrieval, retriever.database
    poses_db = np.asarray(rdb.db.poses, np.float64)
    db_ipa = np.asarray(rdb.db.ipa, np.float64)
    db_ipa = db_ipa / np.maximum(np.linalg.norm(db_ipa, axis=1, keepdims=True), 1e-12)
    cols = images.select(["image_id", "x", "y", "theta"]).to_pydict()
    truth = np.column_stack([cols["x"], cols["y"], cols["theta"]]).astype(np.float64).reshape(-1, 3)
    gt = _boxes_by_image(boxes) if boxes is not None else {}
    hits1, hits4, sims, same, dets = [], [], [], [], []
    k = len(r["candidate_weights"])
    for i, iid in enumerate(progress_bar(cols["image_id"], desc="describe + retrieve", unit="image",
                                         enabled=progress)):
        d = retriever.describer.describe(root / iid)
        regions = d.rpa[d.query_rows(r["query_regions"])]
        found = query_database(rdb, d.ipa, regions, top_n=r["top_n"], weights=tuple(r["candidate_weights"]),
                               rerank=r.get("rerank", True))
        ranked = np.asarray(found.ranked)[: max(k, 4)]
        ok = positives(truth[i : i + 1], poses_db[ranked], position_m, heading_deg)[0]
        hits1.append(bool(ok[:1].any()))
        hits4.append(bool(ok[:4].any()))
        q = d.ipa[None, :] if rdb.ipa_whitening is None else rdb.ipa_whitening.transform(d.ipa[None, :])
        q = np.asarray(q, np.float64)[0]
        q = q / max(float(np.linalg.norm(q)), 1e-12)
        metres = np.hypot(*(poses_db[:, :2] - truth[i, :2]).T)
        turn = np.abs(np.angle(np.exp(1j * (poses_db[:, 2] - truth[i, 2]))))
        j = int(np.argmin(metres + turn))  # metres + radians: the same view first
        sims.append(float(db_ipa[j] @ q))
        same.append(bool(metres[j] <= check.same_place_m and turn[j] <= np.radians(check.same_place_deg)))
        keep = [j for j, m in enumerate(d.meta) if m[0] == "detection"]
        dets.append((d.boxes[keep].reshape(-1, 4), np.array([d.meta[j][1] for j in keep]),
                     np.array([d.meta[j][2] for j in keep], np.int64)))

    def figures(rows: list[int]) -> dict:
        boxed = [j for j in rows if cols["image_id"][j] in gt]
        mapped = None
        if boxed:
            m = coco_map([gt[cols["image_id"][j]][0] for j in boxed], [gt[cols["image_id"][j]][1] for j in boxed],
                         [dets[j][0] for j in boxed], [dets[j][1] for j in boxed], [dets[j][2] for j in boxed],
                         classes)
            mapped = m["map_50"]
        at = [sims[j] for j in rows if same[j]]
        near = [sims[j] for j in rows if not same[j]]
        return {"images": len(rows), "recall_at_1": float(np.mean([hits1[j] for j in rows])),
                "recall_at_4": float(np.mean([hits4[j] for j in rows])),
                "same_place_images": len(at), "same_place_similarity": float(np.median(at)) if at else None,
                "same_place_changed": None if changed_below is None else int(np.sum(np.array(at) < changed_below)),
                "neighbour_similarity": float(np.median(near)) if near else None,
                "images_with_boxes": len(boxed), "detector_map_50": mapped}

    groups: dict[str, list[int]] = {}
    for j, key in enumerate(keys):
        groups.setdefault(key, []).append(j)
    return {"measure_version": MEASURE_VERSION, "position_m": position_m, "heading_deg": heading_deg,
            "areas": {key: figures(rows) for key, rows in sorted(groups.items())},
            "all": figures(list(range(len(keys)))) if keys else None}


def write_baseline(tmp: Path, data: Path, settings: dict, cfg, *, progress: bool = True) -> dict | None:
    """evaluation/baseline.json of the bundle in `tmp`: `measure` on the ingest's test-split stops (the
    images the database was not built from); None when the ingest holds out none."""
    import pyarrow.compute as pc

    from pipeline.io import tables
    from pipeline.io.atomic import write_text_atomic
    from pipeline.io.site import read_site

    images = tables.read_table(data / "images.parquet", "images")
    held_out = images.filter(pc.equal(images.column("split"), "test"))
    if held_out.num_rows == 0:
        return None
    bundle_images = tables.read_table(tmp / "db" / "images.parquet", "images")
    c = cfg.check
    keys = image_keys(held_out, bundle_images, cfg.update.proximity_m)
    doc = measure(BundleRetriever.from_dir(tmp, settings["retrieval"]), data, held_out,
                  tables.read_table(data / "boxes.parquet", "boxes"), keys, check=c,
                  classes=list(read_site(data / "site.yaml").classes), progress=progress)
    doc["images_from"] = "the ingest's test split (stops held out of the database)"
    (tmp / "evaluation").mkdir(exist_ok=True)
    write_text_atomic(tmp / BASELINE_FILE, json.dumps(doc, indent=2) + "\n")
    return doc
