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


def batched_encode(enc, batch: int):
    """An `Encode` (`pipeline.chunked_encoding`) of the torch encoder: image files -> {layer: vectors}."""
    from pipeline.detection.inference import load_image

    def encode(paths: list[Path]) -> dict[str, np.ndarray]:
        parts = [enc([load_image(p) for p in paths[i:i + batch]]) for i in range(0, len(paths), batch)]
        return {name: np.concatenate([part[name] for part in parts]) for name in enc.layers}

    return encode


def _encode(enc, engine: str, paths: list[Path], partial: Path, chunk: int, batch: int, samples: int, bar,
            executor: str, ray_address: str | None) -> tuple[dict[str, np.ndarray], dict]:
    """{layer: vectors} of `paths` in resumable chunks, and with onnx the graphs' parity figures."""
    from pipeline.chunked_encoding import encode_in_chunks, encode_with_graphs, refuse_torch_on_ray

    refuse_torch_on_ray(engine, executor, "prior.engine")
    if engine == "torch":
        return encode_in_chunks(paths, partial, chunk, batched_encode(enc, batch), bar), {}
    import torch

    from pipeline.prior.onnx_export import export_prior_encoder

    def build(hw: tuple[int, int], images: list, path: Path) -> dict:
        return export_prior_encoder(enc, hw, path, [torch.from_numpy(im) for im in images])["parity"]

    return encode_with_graphs("prior", build, list(enc.layers), paths, partial, chunk, bar, samples=samples,
                              executor=executor, ray_address=ray_address)


def run_prior_features(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True, executor: str = "local",
                       ray_address: str | None = None) -> Path:
    """`executor` "ray" runs the encoder's ONNX graph on Ray actors (`pipeline.chunked_encoding`; the same
    vectors as a local run)."""
    from pipeline.descriptors.multilayer import MultiLayerEncoder
    from pipeline.detection.inference import pick_device
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.progress import progress_bar

    p = cfg.prior
    data, out = Path(inputs["data"]), Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    cols = labelled_images(data)
    from pipeline.onnx_threads import resolve_engine

    device = pick_device(p.device)
    engine = resolve_engine(p.engine, device.type)
    # onnxruntime runs on the CPU here: the torch encoder it is checked against lives there too.
    enc = MultiLayerEncoder(p.backbone, p.weights, p.input_size, device="cpu" if engine == "onnx" else str(device))
    from pipeline.io.image_reuse import EarlierImages, encoder_key, image_hashes, state_digest, write_hashes

    ids = cols["image_id"]
    sha = image_hashes(data, ids)
    key = encoder_key("prior-features", state_digest(enc.model), p.backbone, p.input_size, list(enc.layers), engine)
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
    from pipeline.chunked_encoding import close_partial, open_partial

    partial = out.with_name(out.name + ".partial")
    todo_paths = [data / ids[k] for k in todo]
    open_partial(partial, {"stage": "prior-features", "encoder": key, "chunk": p.chunk, "batch": p.batch,
                           "device": str(enc.device)}, todo_paths, force=force)
    where = f"{p.backbone} layers ({engine}" + (", ray)" if executor == "ray" else ")")
    bar = progress_bar(total=len(todo), desc=where, unit="image", enabled=progress)
    try:
        fresh, graphs = _encode(enc, engine, todo_paths, partial, p.chunk, p.batch, cfg.export.parity_images, bar,
                                executor, ray_address)
    finally:
        bar.close()
    for name, v in fresh.items():
        for k, row in zip(todo, v, strict=True):
            rows[name][k] = row
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
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
            "engine": engine, **({"onnx": graphs} if graphs else {}),
            **({"reuse": {"from": str(inputs["reuse"]), "encoder_matches": earlier.matches,
                          "reused_images": len(ids) - len(todo)}} if earlier is not None else {})},
            indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="prior-features", inputs=inputs)
    close_partial(partial)
    return out
