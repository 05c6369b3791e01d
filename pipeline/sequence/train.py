"""Stage `train-sequence`: the image-sequence LSTM and its database (seed 000 section 3.3).

Input: `frame-features` output (frames.parquet). Training windows: every `sequence.length`
consecutive frames of the mapping runs, labelled with the place of their last frame (see `model`);
Adam (lr 1e-3) on batches of 75 as in the paper, seeded, `epochs` passes. A checkpoint after each
epoch (tensors and primitives, with a fingerprint of the settings and frames) lets an interrupted
training resume; another training's checkpoint is refused. Then every mapping window is described
(mean-pooled LSTM outputs), PCA-whitening is fitted on them, and the whitened descriptors with the
poses of their last frames become the sequence database.

Measured on the query runs' windows (none crossing a kidnapping): recall@{1, 4} of a database window
within 2 m of the query's last frame, for the sequence descriptor at lengths 1..10 and for single
frames (whitened logits), with the time per query.

Outputs: weights.safetensors, config.json (builder arguments, places), database.parquet (kind
`sequences`), whitening.npz, metrics.json, config.yaml, and for DVC (`pipeline.io.tracked`)
headline.json (recall@1 within 2 m at the configured `sequence.length` and for single frames) and
plots/loss.csv (`epoch,loss`: the mean training loss of each epoch, 1-based).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem
from pipeline.io import tables


class Frames:
    """frames.parquet as arrays, rows grouped by run in step order."""

    def __init__(self, path: Path):
        t = tables.read_table(Path(path), "frames")
        cols = t.select(["run", "step", "gt_x", "gt_y", "gt_theta"]).to_pydict()
        order = sorted(range(t.num_rows), key=lambda i: (cols["run"][i], cols["step"][i]))
        self.run = np.asarray(cols["run"])[order]
        self.step = np.asarray(cols["step"], np.int64)[order]
        self.pose = np.column_stack([np.asarray([np.nan if v is None else v for v in cols[k]], np.float64)[order]
                                     for k in ("gt_x", "gt_y", "gt_theta")])
        self.features = tables.descriptor_matrix(t)[order].astype(np.float32)

    def windows(self, runs: list[str], length: int, breaks: dict[str, np.ndarray] | None = None) -> np.ndarray:
        from pipeline.sequence.model import windows

        out = []
        for r in runs:
            rows = np.flatnonzero(self.run == r)
            b = breaks.get(r, np.zeros(len(rows), bool)) if breaks else np.zeros(len(rows), bool)
            out.append(rows[windows(self.step[rows], b, length)])
        return np.concatenate(out) if out else np.zeros((0, length), np.int64)


def kidnap_breaks(data: Path | None, frames: Frames) -> dict[str, np.ndarray]:
    """Per run, which frame rows start after a kidnapping (windows must not span one)."""
    if data is None:
        return {}
    out = {}
    for r in sorted(set(frames.run)):
        path = Path(data) / "runs" / f"{r}.parquet"
        if not path.is_file():
            continue
        t = tables.read_table(path, "runs").select(["step", "kidnapped"]).to_pydict()
        kid = {s for s, k in zip(t["step"], t["kidnapped"], strict=True) if k}
        rows = np.flatnonzero(frames.run == r)
        out[r] = np.array([int(s) in kid for s in frames.step[rows]])
    return out


def _fingerprint(s, frames: Frames, n_places: int) -> str:
    h = hashlib.sha256(json.dumps(s.model_dump(mode="json"), sort_keys=True).encode())
    h.update(frames.features.tobytes())
    h.update(str(n_places).encode())
    return h.hexdigest()


def describe_windows(model, features: np.ndarray, win: np.ndarray, batch: int = 512) -> np.ndarray:
    import torch

    out = []
    with torch.no_grad():
        for i in range(0, len(win), batch):
            out.append(model.describe(torch.from_numpy(features[win[i:i + batch]])).numpy())
    return np.vstack(out) if out else np.zeros((0, model.lstm.hidden_size), np.float32)


def recall_within(found_xy: np.ndarray, query_xy: np.ndarray, radius: float) -> float:
    """Share of queries whose any of the found poses (Q, K, 2) lies within `radius` of the query's."""
    d = np.hypot(*(found_xy - query_xy[:, None, :]).transpose(2, 0, 1))
    return float(np.mean((d <= radius).any(axis=1))) if len(d) else float("nan")


def run_train_sequence(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True) -> Path:
    import torch
    from safetensors.torch import save_file

    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.io.checkpoint import resume_state, save_checkpoint
    from pipeline.progress import progress_bar
    from pipeline.retrieval.whitening import PCAWhitening
    from pipeline.sequence.model import build_sequence_model, place_labels

    s = cfg.sequence
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    frames_path = Path(inputs["frames"]) / "frames.parquet"
    frames = Frames(frames_path)
    mapping = sorted(r for r in set(frames.run) if r.startswith("mapping"))
    queries = sorted(r for r in set(frames.run) if r.startswith("query"))
    train = frames.windows(mapping, s.length)
    if len(train) < 2:
        raise InputError(f"{frames_path}: {len(train)} training windows of {s.length} frames",
                         [Problem(str(frames_path), "mapping runs (run names starting 'mapping') give the windows",
                                  fix="extract frame features of a site with mapping runs, or lower sequence.length")])
    last = train[:, -1]
    labels, places = place_labels(frames.pose[last, :2], frames.pose[last, 2], s.place_cell_m, s.heading_bins)
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    model = build_sequence_model(frames.features.shape[1], s.hidden, len(places))
    opt = torch.optim.Adam(model.parameters(), lr=s.lr)
    partial = out.with_name(out.name + ".partial")
    ckpt_path = partial / "checkpoint.pt"
    fingerprint = _fingerprint(s, frames, len(places))
    start, history = 0, []
    ckpt = resume_state(ckpt_path, fingerprint, force=force, what="other sequence settings or frames")
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        start, history = int(ckpt["epoch"]), [float(v) for v in ckpt["history"]]
        rng = np.random.default_rng(int(ckpt["rng_seed"]))
        torch.set_rng_state(ckpt["torch_rng"])
    x_all, y_all = torch.from_numpy(frames.features), torch.from_numpy(labels)
    t0 = time.perf_counter()
    model.train()
    for epoch in progress_bar(range(start, s.epochs), desc="training sequence LSTM", unit="epoch", enabled=progress,
                              total=s.epochs - start):
        order = rng.permutation(len(train))
        total = 0.0
        for i in range(0, len(order), s.train_batch):
            b = order[i:i + s.train_batch]
            loss = torch.nn.functional.cross_entropy(model(x_all[train[b]]), y_all[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
        history.append(total / len(order))
        partial.mkdir(parents=True, exist_ok=True)
        seed_next = int(rng.integers(0, 2**31))
        rng = np.random.default_rng(seed_next)
        save_checkpoint(ckpt_path, {"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch + 1,
                                    "history": history, "rng_seed": seed_next,
                                    "torch_rng": torch.get_rng_state()}, fingerprint)
    train_s = time.perf_counter() - t0
    model.eval()
    db_desc = describe_windows(model, frames.features, train)
    whitening = PCAWhitening(s.dims).fit(db_desc)
    db = whitening.transform(db_desc)
    metrics = {"train_windows": int(len(train)), "places": len(places), "epochs": s.epochs,
               "loss_history": history, "train_seconds": round(train_s, 2),
               "dims": int(whitening.n_components_), "dims_cap": str(whitening.cap_reason_),
               "query_runs": queries,
               "recall": evaluate_lengths(model, whitening, db, frames, train, queries,
                                          kidnap_breaks(inputs.get("data"), frames))}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(tmp / "weights.safetensors"))
        write_text_atomic(tmp / "config.json", json.dumps({
            "builder": {"in_dim": int(frames.features.shape[1]), "hidden": s.hidden, "num_places": len(places)},
            "length": s.length, "places": [list(p) for p in places], "place_cell_m": s.place_cell_m,
            "heading_bins": s.heading_bins, "frames": str(frames_path),
            # how the frames were encoded: the runtime's camera images must be encoded the same way
            "frame_encoder": tables.table_metadata(tables.read_table(frames_path, "frames"))}, indent=2) + "\n")
        whitening.save(tmp / "whitening.npz")
        write_database(tmp / "database.parquet", frames, last, db, s.length)
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_tracked(tmp, metrics, s.length)
        write_effective_config(cfg, tmp, stage="train-sequence", inputs=inputs)
    if ckpt_path.exists():
        ckpt_path.unlink()
        partial.rmdir()
    return out


def write_database(path: Path, frames: Frames, last: np.ndarray, db: np.ndarray, length: int) -> Path:
    """database.parquet (kind `sequences`): each window's whitened descriptor and its last frame's pose."""
    return tables.write_table(path, tables.to_table("sequences", {
        "run": frames.run[last].tolist(), "end_step": frames.step[last].tolist(),
        "x": frames.pose[last, 0], "y": frames.pose[last, 1], "theta": frames.pose[last, 2],
        "descriptor": tables.descriptor_array(db.astype(np.float32))}), "sequences", metadata={"length": str(length)})


def headline(metrics: dict, length: int) -> dict:
    """The figures compared across retrains: recall@1 within 2 m of the sequence descriptor at the
    configured length (key `recall_at_1_2m_<length>_frames`, the paper's 6 by default) and of single
    frames; None where there were no query windows."""
    recall = metrics.get("recall", {})
    return {f"recall_at_1_2m_{length}_frames": recall.get(f"length_{length}", {}).get("recall_at_1_2m"),
            "recall_at_1_2m_single_frame": recall.get("single_frame", {}).get("recall_at_1_2m")}


def write_tracked(out: Path, metrics: dict, length: int) -> None:
    """headline.json (`headline`) and plots/loss.csv (`epoch,loss`, epoch n: the mean loss of the n-th pass)."""
    from pipeline.io.tracked import write_headline, write_plot_table

    write_headline(out, headline(metrics, length))
    write_plot_table(out, "loss", ["epoch", "loss"], enumerate(metrics["loss_history"], start=1))


def evaluate_lengths(model, whitening, db: np.ndarray, frames: Frames, train: np.ndarray, queries: list[str],
                     breaks: dict, lengths=range(1, 11)) -> dict:
    """Recall@{1, 4} within 2 m on the query runs for each sequence length, and for single whitened frames."""
    from pipeline.retrieval.whitening import PCAWhitening

    if not queries:
        return {}
    db_xy = frames.pose[train[:, -1], :2]
    out = {}
    for n in lengths:
        win = frames.windows(queries, n, breaks)
        if not len(win):
            continue
        t0 = time.perf_counter()
        q = whitening.transform(describe_windows(model, frames.features, win))
        top = np.argsort(-(q @ db.T), axis=1)[:, :4]
        ms = (time.perf_counter() - t0) * 1000.0 / len(win)
        out[f"length_{n}"] = {**_recalls(db_xy[top], frames.pose[win[:, -1], :2], db_xy), "queries": int(len(win)),
                              "ms_per_query": round(ms, 4)}
    rows = np.unique(train[:, -1])
    single = PCAWhitening(whitening.n_components_).fit(frames.features[rows])
    qrows = np.flatnonzero(np.isin(frames.run, queries))
    top = np.argsort(-(single.transform(frames.features[qrows]) @ single.transform(frames.features[rows]).T),
                     axis=1)[:, :4]
    dxy = frames.pose[rows, :2]
    out["single_frame"] = {**_recalls(dxy[top], frames.pose[qrows, :2], dxy), "queries": int(len(qrows))}
    return out


def _recalls(found_xy: np.ndarray, query_xy: np.ndarray, db_xy: np.ndarray, radius: float = 2.0) -> dict:
    """Recall@1 and @4 within `radius`, over all queries and over the reachable ones (those with any
    database entry within `radius`: the mapping runs do not pass everywhere the query runs go)."""
    reach = (np.hypot(*(query_xy[:, None, :] - db_xy[None]).transpose(2, 0, 1)) <= radius).any(axis=1)
    out = {"reachable_2m": float(reach.mean()) if len(reach) else float("nan")}
    for k in (1, 4):
        out[f"recall_at_{k}_2m"] = recall_within(found_xy[:, :k], query_xy, radius)
        out[f"recall_at_{k}_reachable_2m"] = recall_within(found_xy[reach, :k], query_xy[reach], radius)
    return out
