"""Stage `prior features`: seed 001's multi-layer CNN vectors of every capture image of a site.

Input: an ingested site (images.parquet with room and area labels, images/). Each image goes through a
pretrained CNN (`pipeline.descriptors.multilayer`); the three layers' l2-normalised raw vectors are
written one Parquet file per layer (`<layer>.parquet`, kind `multilayer`: image_id, stop, room, area,
split, pose, descriptor), with report.json and config.yaml. `prior build` compresses and indexes them;
keeping them raw lets every compression be compared on the same vectors (the paper's Table I). With
`inputs['reuse']` (an earlier output), the vectors of images whose bytes it has seen under the same encoder
are copied and only the others computed (pipeline.io.image_reuse).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io import tables

META_COLUMNS = ("image_id", "stop_id", "room", "area", "split", "x", "y", "theta")


def labelled_images(data: Path) -> dict[str, list]:
    """The site's images with their (room, area) classes; every image needs both labels."""
    t = tables.read_table(Path(data) / "images.parquet", "images")
    cols = {c: t.column(c).to_pylist() for c in META_COLUMNS}
    unlabelled = [i for i, (r, a) in enumerate(zip(cols["room"], cols["area"], strict=True)) if not r or not a]
    if unlabelled:
        raise InputError(f"{data}: {len(unlabelled)} images have no room or area label", [Problem(
            f"{Path(data) / 'images.parquet'} row {i}", f"image '{cols['image_id'][i]}' has room "
            f"{cols['room'][i]!r}, area {cols['area'][i]!r}",
            fix="give every capture image a room and an area (captures.csv columns room, area) and ingest again")
            for i in unlabelled[:10]])
    missing = [m for m in cols["image_id"] if not (Path(data) / m).is_file()]
    if missing:
        raise InputError(f"{data}: {len(missing)} images are missing",
                         [Problem(str(Path(data) / m), "file is missing", fix="re-run `siteloc ingest`")
                          for m in missing[:10]])
    return cols


def read_layers(features: Path) -> tuple[dict[str, list], dict[str, np.ndarray], dict]:
    """(metadata columns, {layer: (N, D) raw vectors}, report) of a `prior features` output."""
    features = Path(features)
    report_path = features / "report.json"
    if not report_path.is_file():
        raise InputError(f"{features}: not a `siteloc prior features` output", [Problem(
            str(report_path), "missing", fix="run `siteloc prior features DATA --out DIR` and point at DIR")])
    report = json.loads(report_path.read_text())
    meta, vectors = None, {}
    for layer in report["encoder"]["layers"]:
        t = tables.read_table(features / f"{layer}.parquet", "multilayer")
        cols = {c: t.column(c).to_pylist() for c in META_COLUMNS}
        if meta is not None and cols["image_id"] != meta["image_id"]:
            raise InputError(f"{features}: layer files disagree", [Problem(
                str(features / f"{layer}.parquet"), "its images differ from the first layer's",
                fix="run `siteloc prior features` again with --force")])
        meta = meta or cols
        vectors[layer] = tables.descriptor_matrix(t)
    return meta, vectors, report


def select(meta: dict, raw: dict[str, np.ndarray], rows) -> tuple[dict, dict[str, np.ndarray]]:
    """The rows (indices, or a boolean mask) of `read_layers`' metadata columns and layer vectors."""
    rows = np.asarray(rows)
    idx = np.flatnonzero(rows) if rows.dtype == bool else rows
    return {k: [v[i] for i in idx] for k, v in meta.items()}, {n: v[idx] for n, v in raw.items()}


def run_prior_features(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True) -> Path:
    from pipeline.descriptors.multilayer import MultiLayerEncoder
    from pipeline.detection.inference import load_image, pick_device
    from pipeline.errors import OutputExistsError
    from pipeline.io.atomic import atomic_dir, write_text_atomic
    from pipeline.progress import progress_bar

    p = cfg.prior
    data, out = Path(inputs["data"]), Path(outputs["out"])
    if out.exists() and not force:
        raise OutputExistsError(out)
    cols = labelled_images(data)
    enc = MultiLayerEncoder(p.backbone, p.weights, p.input_size, device=str(pick_device(p.device)))
    from pipeline.io.image_reuse import EarlierImages, encoder_key, image_hashes, state_digest, write_hashes

    ids = cols["image_id"]
    sha = image_hashes(data, ids)
    key = encoder_key("prior-features", state_digest(enc.model), p.backbone, p.input_size, list(enc.layers))
    earlier = (EarlierImages(inputs["reuse"], key, report_field="encoder_sha256", stage="prior features")
               if inputs.get("reuse") else None)
    rows: dict[str, list] = {name: [None] * len(ids) for name in enc.layers}
    if earlier is not None and earlier.matches:
        old_meta, old_raw, _ = read_layers(earlier.directory)
        at = {i: k for k, i in enumerate(old_meta["image_id"])}
        for k, image_id in enumerate(ids):
            j = at.get(earlier.image_id(sha[image_id]))
            if j is not None:
                for name in enc.layers:
                    rows[name][k] = old_raw[name][j]
    todo = [k for k in range(len(ids)) if rows[enc.layers[0]][k] is None]
    bar = progress_bar(total=len(todo), desc=f"{p.backbone} layers", unit="image", enabled=progress)
    for i in range(0, len(todo), p.batch):
        batch = todo[i:i + p.batch]
        for name, v in enc([load_image(data / ids[k]) for k in batch]).items():
            for k, row in zip(batch, v, strict=True):
                rows[name][k] = row
        bar.update(len(batch))
    bar.close()
    with atomic_dir(out, force=force) as tmp:
        dims = {}
        write_hashes(tmp, sha, ids)
        for name in enc.layers:
            matrix = np.stack(rows[name]).astype(np.float32)
            dims[name] = int(matrix.shape[1])
            tables.write_table(tmp / f"{name}.parquet", tables.to_table(
                "multilayer", {**cols, "descriptor": tables.descriptor_array(matrix)}), "multilayer",
                metadata={"layer": name, "backbone": p.backbone, "weights": enc.source})
        splits = {s: cols["split"].count(s) for s in sorted(set(cols["split"]))}
        write_text_atomic(tmp / "report.json", json.dumps({
            "data": str(data), "images": len(ids), "splits": splits,
            "classes": len(set(zip(cols["room"], cols["area"], strict=True))), "rooms": len(set(cols["room"])),
            "encoder": enc.describe(), "dims": dims, "encoder_sha256": key, "computed_images": len(todo),
            **({"reuse": {"from": str(inputs["reuse"]), "encoder_matches": earlier.matches,
                          "reused_images": len(ids) - len(todo)}} if earlier is not None else {})},
            indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="prior-features", inputs=inputs)
    return out
