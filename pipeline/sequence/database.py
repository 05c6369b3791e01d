"""`train-sequence --keep-model`: a new sequence database from new frames, described by a trained LSTM.

After `siteloc update` the mapping runs are recorded again, and `frame-features --reuse` encodes only the
frames whose bytes changed. The LSTM and its whitening are kept as they are: every mapping window of the
new frames is described and whitened with them, so a window of unchanged frames gets the descriptor it
had (to float rounding of the batch), and only the windows that see a change differ. Nothing is trained;
the query runs' recalls are measured as `train-sequence` measures them.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io import tables

MODEL_FILES = ("weights.safetensors", "config.json", "whitening.npz")


def _encoder_of(meta: dict) -> tuple:
    """What makes two frame-features outputs comparable: the encoder's weights (by file name) and size."""
    return Path(meta.get("weights", "")).name, str(meta.get("frame_size"))


def run_sequence_database(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                          force: bool = False) -> Path:
    """`outputs['out']`: the model of `inputs['model']` with a database of `inputs['frames']`' mapping runs."""
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.retrieval.whitening import PCAWhitening
    from pipeline.sequence import train as T
    from pipeline.sequence.onnx_export import load_sequence_model

    out, model_dir = Path(outputs["out"]), Path(inputs["model"])
    check_output(out, force=force, inputs=inputs.values())
    missing = [f for f in MODEL_FILES if not (model_dir / f).is_file()]
    if missing:
        raise InputError(f"{model_dir}: not a `siteloc train-sequence` output", [Problem(
            str(model_dir / f), "missing", fix="point --keep-model at the sequence model of the bundle in use")
            for f in missing])
    model, seq_cfg = load_sequence_model(model_dir)
    frames_path = Path(inputs["frames"]) / "frames.parquet"
    frames = T.Frames(frames_path)
    found = tables.table_metadata(tables.read_table(frames_path, "frames"))
    used = seq_cfg.get("frame_encoder") or {}
    if frames.features.shape[1] != seq_cfg["builder"]["in_dim"] or (used and _encoder_of(used) != _encoder_of(found)):
        raise InputError(f"{frames_path}: encoded otherwise than the frames the model was trained on", [Problem(
            str(frames_path), f"{frames.features.shape[1]}-d, weights {found.get('weights')}, size "
            f"{found.get('frame_size')}; the model's: {seq_cfg['builder']['in_dim']}-d, weights "
            f"{used.get('weights')}, size {used.get('frame_size')}",
            fix="run `siteloc frame-features` with the sequence settings (--config) the model was trained with")])
    length = int(seq_cfg["length"])
    mapping = sorted(r for r in set(frames.run) if r.startswith("mapping"))
    queries = sorted(r for r in set(frames.run) if r.startswith("query"))
    windows = frames.windows(mapping, length)
    if not len(windows):
        raise InputError(f"{frames_path}: no mapping window of {length} frames", [Problem(
            str(frames_path), "mapping runs (run names starting 'mapping') give the database",
            fix="extract the frame features of the updated site, whose runs include the mapping runs")])
    whitening = PCAWhitening.load(model_dir / "whitening.npz")
    db = whitening.transform(T.describe_windows(model, frames.features, windows))
    metrics = {"train_windows": int(len(windows)), "places": len(seq_cfg["places"]), "epochs": 0,
               "loss_history": [], "kept_model": str(model_dir), "dims": int(whitening.n_components_),
               "dims_cap": str(whitening.cap_reason_), "query_runs": queries,
               "recall": T.evaluate_lengths(model, whitening, db, frames, windows, queries,
                                            T.kidnap_breaks(inputs.get("data"), frames))}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        for f in ("weights.safetensors", "whitening.npz"):
            shutil.copyfile(model_dir / f, tmp / f)
        write_text_atomic(tmp / "config.json", json.dumps({**seq_cfg, "frames": str(frames_path),
                                                           "model_from": str(model_dir)}, indent=2) + "\n")
        T.write_database(tmp / "database.parquet", frames, windows[:, -1], db, length)
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        T.write_tracked(tmp, metrics, length)
        write_effective_config(cfg, tmp, stage="train-sequence --keep-model", inputs=inputs)
    return out
