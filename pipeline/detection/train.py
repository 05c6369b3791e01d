"""Stage `train-detector`: fine-tune the 9-class Faster R-CNN on an ingested site.

SGD with momentum and weight decay, the learning rate warming up linearly, then dropping 10x after
`lr_drop_at` of the iterations (the paper's 1e-3 then 1e-4); on a GPU with float16 autocast and gradient
scaling unless `amp` is off; batches drawn from the training stops (the ingest's `train` split minus a
seeded share of stops held for validation), uniformly or, with `repeat_factor_threshold`, favouring
images of rare classes; flips and colour jitter. Every `checkpoint_every`
iterations a checkpoint of tensors and primitives only (model, optimizer, iteration, generator states)
is written atomically to `<out>.partial/checkpoint.pt`; a rerun resumes from it (`torch.load` with
weights_only=True). A non-finite loss stops training with an error naming the iteration. The finished
output directory holds `weights.safetensors`, `config.json` (builder arguments, classes, weights source,
iterations), `metrics.json` (loss curve, validation loss, timings), `headline.json` (loss_first,
loss_last_50_mean, val_loss) and `plots/loss.csv` (`iteration,loss`: the training loss at each 0-based
iteration, as `loss_history`), which DVC compares across runs (`pipeline.io.tracked`).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import SitelocError


class TrainingError(SitelocError):
    """Training cannot go on (a non-finite loss, no training images)."""


def _collate(batch):
    return [b[0] for b in batch], [{k: v for k, v in b[1].items() if k != "scale"} for b in batch]


def _to(device, images, targets):
    images = [im.to(device, non_blocking=True) for im in images]
    return images, [{k: v.to(device) for k, v in t.items()} for t in targets]


def _loss(model, images, targets):
    losses = model(images, targets)
    return sum(losses.values()), {k: float(v.detach()) for k, v in losses.items()}


def run_train_detector(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                       force: bool = False, progress: bool = True) -> Path:
    import torch
    from safetensors.torch import save_file

    from pipeline.detection.builders import build_detector, use_channels_last
    from pipeline.detection.data import DetectionDataset, load_samples, repeat_factors, split_by_stop
    from pipeline.detection.inference import pick_device
    from pipeline.io.atomic import atomic_dir, write_text_atomic
    from pipeline.io.checkpoint import resume_state, save_checkpoint
    from pipeline.io.tracked import write_headline, write_plot_table
    from pipeline.progress import progress_bar

    d = cfg.detector
    out = Path(outputs["out"])
    if out.exists() and not force:
        from pipeline.errors import OutputExistsError

        raise OutputExistsError(out)
    _, splits, classes = load_samples(Path(inputs["data"]))
    train, val = split_by_stop(splits.get("train", []), d.val_fraction, d.seed)
    train = [s for s in train if len(s.boxes)]
    if not train:
        raise TrainingError(f"{inputs['data']}: no training image has a box")
    torch.manual_seed(d.seed)
    rng = np.random.default_rng(d.seed)
    args = dict(backbone=d.backbone, num_classes=len(classes) + 1, min_size=d.min_size, max_size=d.max_size,
                anchor_sizes=tuple(d.anchor_sizes), rpn_post_nms_top_n_test=d.rpn_post_nms_top_n_test,
                box_nms_thresh=d.box_nms_thresh,
                frozen_batch_norm=d.weights is not None)
    built = build_detector(weights=d.weights, **args)
    device = pick_device(d.device)
    amp = d.amp and device.type == "cuda"
    model = built.model.to(device)
    use_channels_last(model)
    opt = torch.optim.SGD(param_groups(model, d), lr=d.lr, momentum=d.momentum, weight_decay=d.weight_decay)
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    partial = out.with_name(out.name + ".partial")
    ckpt_path = partial / "checkpoint.pt"
    start, history = 0, []
    fingerprint = _fingerprint(d, train)
    ckpt = resume_state(ckpt_path, fingerprint, force=force, error=TrainingError,
                        what="other detector settings or training images")
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        if amp and ckpt.get("scaler"):
            scaler.load_state_dict(ckpt["scaler"])
        start, history = int(ckpt["iteration"]), [float(v) for v in ckpt["history"]]
        rng = np.random.default_rng(int(ckpt["rng_seed"]))
        torch.set_rng_state(ckpt["torch_rng"])
    data = DetectionDataset(train, max_side=d.max_side, augment=True, seed=int(rng.integers(0, 2**31)))
    draw = repeat_factors(train, d.repeat_factor_threshold)
    draw /= draw.sum()
    model.train()
    t0 = time.perf_counter()
    bar = progress_bar(total=d.iterations, desc=f"training ({device.type})", unit="it", enabled=progress)
    bar.update(start)
    for it in range(start, d.iterations):
        for g in opt.param_groups:
            g["lr"] = learning_rate(it, d) * g["lr_factor"]
        batch = [data[int(i)] for i in rng.choice(len(data), size=d.batch_size, p=draw)]
        images, targets = _to(device, *_collate(batch))
        with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=amp):
            loss, parts = _loss(model, images, targets)
        if not math.isfinite(loss.item()):
            raise TrainingError(f"non-finite loss at iteration {it}: {parts}; lower detector.lr or check the boxes")
        opt.zero_grad()
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
        history.append(loss.item())
        bar.update(1)
        bar.set_postfix(loss=f"{history[-1]:.3f}", refresh=False)
        if (it + 1) % d.checkpoint_every == 0 and it + 1 < d.iterations:
            partial.mkdir(parents=True, exist_ok=True)
            seed_next = int(rng.integers(0, 2**31))
            rng = np.random.default_rng(seed_next)
            save_checkpoint(ckpt_path, {"model": model.state_dict(), "optimizer": opt.state_dict(),
                                        "iteration": it + 1, "history": history, "rng_seed": seed_next,
                                        "torch_rng": torch.get_rng_state(),
                                        "scaler": scaler.state_dict() if amp else {}}, fingerprint)
    bar.close()
    train_s = time.perf_counter() - t0
    model.eval()
    val_loss = _validation_loss(model, val, d.max_side, device)
    with atomic_dir(out, force=force) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
                  str(tmp / "weights.safetensors"))
        write_text_atomic(tmp / "config.json", json.dumps({
            "builder": args, "classes": classes, "weights_source": built.weights_source,
            "max_side": d.max_side, "iterations": d.iterations, "frozen": built.frozen,
            "device": str(device), "mixed_precision": amp,
            "val_stops": sorted({s.stop_id for s in val})}, indent=2) + "\n")
        metrics = {
            "train_images": len(train), "val_images": len(val), "loss_first": history[0], "loss_last": history[-1],
            "loss_last_50_mean": float(np.mean(history[-50:])), "val_loss": val_loss,
            "iterations_per_s": round((d.iterations - start) / max(train_s, 1e-9), 3), "loss_history": history}
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_headline(tmp, {k: metrics[k] for k in ("loss_first", "loss_last_50_mean", "val_loss")})
        # history[i] is the loss of loop iteration i (0-based, as `learning_rate(it)` and the error messages)
        write_plot_table(tmp, "loss", ["iteration", "loss"], enumerate(history))
        write_effective_config(cfg, tmp, stage="train-detector", inputs=inputs)
    if ckpt_path.exists():
        ckpt_path.unlink()
        partial.rmdir()
    return out


def _fingerprint(d, train) -> str:
    """What a checkpoint must share with this training to be resumed by it: the detector section and the
    training images (a checkpoint of another training must never be silently continued)."""
    import hashlib

    doc = {"detector": d.model_dump(mode="json"), "train": sorted(s.image_id for s in train)}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def param_groups(model, d) -> list[dict]:
    """Trainable weights, and biases with py-faster-rcnn's options (their own lr factor, decay or not)."""
    weights = [p for n, p in model.named_parameters() if p.requires_grad and not n.endswith(".bias")]
    biases = [p for n, p in model.named_parameters() if p.requires_grad and n.endswith(".bias")]
    return [{"params": weights, "lr_factor": 1.0},
            {"params": biases, "lr_factor": d.bias_lr_factor, "weight_decay": d.weight_decay if d.bias_decay else 0.0}]


def learning_rate(it: int, d) -> float:
    """Linear warm-up from lr/100 over `warmup_iterations`, then lr, then lr/10 after `lr_drop_at`."""
    base = d.lr * (0.1 if it >= int(d.lr_drop_at * d.iterations) else 1.0)
    if it < d.warmup_iterations:
        return base * (0.01 + 0.99 * it / d.warmup_iterations)
    return base


def _validation_loss(model, samples, max_side, device) -> float | None:
    """Mean training loss on the validation stops (the detector in train mode, no gradients, no augmentation)."""
    import torch

    from pipeline.detection.data import DetectionDataset

    samples = [s for s in samples if len(s.boxes)]
    if not samples:
        return None
    data = DetectionDataset(samples, max_side=max_side)
    model.train()
    total = []
    with torch.no_grad():
        for i in range(0, len(data), 4):
            loss, _ = _loss(model, *_to(device, *_collate([data[j] for j in range(i, min(i + 4, len(data)))])))
            total.append(float(loss))
    model.eval()
    return float(np.mean(total))
