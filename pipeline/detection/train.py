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

With `inputs["init_from"]` (an earlier output of this stage, `--init-from`) training starts from that model's
weights instead of `detector.weights`: after `siteloc update` the detector is fine-tuned on the updated site
rather than trained again from ImageNet. The earlier model must have been built with the builder arguments and
classes this run builds (checked before anything is trained or written); its `weights.safetensors` is loaded
tensors-only and strictly. Which layers train and whether batch norms are frozen still follow the configured
`detector.weights`, as without `--init-from`. `config.json` records `init_from` (path and the sha256 of the
weights loaded), and the checkpoint fingerprint includes that sha256, so a resume never mixes two starts.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem, SitelocError


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
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.io.checkpoint import resume_state, save_checkpoint
    from pipeline.io.tracked import write_headline, write_plot_table
    from pipeline.progress import progress_bar

    d = cfg.detector
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    init_dir = Path(inputs["init_from"]) if inputs.get("init_from") is not None else None
    if init_dir is not None:
        _init_files(init_dir)  # before reading the site: a mistyped path fails at once
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
    init_from, init_state = (None, None) if init_dir is None else _init_from(init_dir, args, classes)
    # With --init-from the configured weights are not loaded (they would be overwritten), but they still decide
    # the frozen batch norms (in `args`) and the frozen layers, so the fine-tuning is the one they would give.
    built = build_detector(weights=None if init_dir is not None else d.weights, **args)
    weights_source = built.weights_source
    if init_state is not None:
        try:
            built.model.load_state_dict(init_state, strict=True)
        except RuntimeError as exc:
            w = init_dir / "weights.safetensors"
            raise InputError(f"--init-from {init_dir}: the weights do not fit the network in its config.json", [
                Problem(str(w), str(exc).splitlines()[0],
                        fix="point --init-from at a `siteloc train-detector` output whose files belong together")],
            ) from None
        weights_source = f"init-from: {init_dir} (weights.safetensors sha256 {init_from['weights_sha256'][:12]})"
        del init_state
    device = pick_device(d.device)
    amp = d.amp and device.type == "cuda"
    model = built.model.to(device)
    use_channels_last(model)
    opt = torch.optim.SGD(param_groups(model, d), lr=d.lr, momentum=d.momentum, weight_decay=d.weight_decay)
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    partial = out.with_name(out.name + ".partial")
    ckpt_path = partial / "checkpoint.pt"
    start, history = 0, []
    fingerprint = _fingerprint(d, train, init_from)
    ckpt = resume_state(ckpt_path, fingerprint, force=force, error=TrainingError,
                        what="other detector settings, training images or --init-from weights")
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
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
                  str(tmp / "weights.safetensors"))
        record = {"builder": args, "classes": classes, "weights_source": weights_source}
        if init_from is not None:
            record["init_from"] = init_from
        write_text_atomic(tmp / "config.json", json.dumps({
            **record, "max_side": d.max_side, "iterations": d.iterations, "frozen": built.frozen,
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


def _fingerprint(d, train, init_from: dict | None = None) -> str:
    """What a checkpoint must share with this training to be resumed by it: the detector section, the
    training images and, with --init-from, the sha256 of the weights it started from (a checkpoint of another
    training must never be silently continued). Without --init-from the fingerprint is the one it always was."""
    import hashlib

    doc = {"detector": d.model_dump(mode="json"), "train": sorted(s.image_id for s in train)}
    if init_from is not None:
        doc["init_from_sha256"] = init_from["weights_sha256"]
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


_INIT_FIX = "point --init-from at a `siteloc train-detector` output (weights.safetensors + config.json)"


def _init_files(init_dir: Path) -> tuple[Path, Path]:
    """config.json and weights.safetensors of an --init-from directory, or InputError naming what is missing."""
    files = (init_dir / "config.json", init_dir / "weights.safetensors")
    if not init_dir.is_dir():
        missing = [Problem(str(init_dir), "no such directory", fix=_INIT_FIX)]
    else:
        missing = [Problem(str(f), "missing", fix=_INIT_FIX) for f in files if not f.is_file()]
    if missing:
        raise InputError(f"--init-from {init_dir}: not a trained detector", missing)
    return files


# What to change when a builder argument of the --init-from model differs from this run's.
_BUILDER_FIX = {
    "num_classes": "the site's classes must be the model's",
    "frozen_batch_norm": "frozen batch norms follow detector.weights (frozen unless it is null); set detector.weights "
                         "as the model was trained (with --init-from those weights are not loaded)",
}


def _init_from(init_dir: Path, args: dict, classes: list[str]) -> tuple[dict, dict]:
    """Check an --init-from model against the network this run builds; its record for config.json (path, sha256
    of the weights) and its state dict (read with safetensors, never unpickled)."""
    import hashlib

    from safetensors import SafetensorError
    from safetensors.torch import load as load_safetensors

    cfg_path, weights_path = _init_files(init_dir)
    try:
        old = json.loads(cfg_path.read_text())
        old_builder, old_classes = old["builder"], old["classes"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise InputError(f"--init-from {init_dir}: unreadable config.json", [
            Problem(str(cfg_path), f"not a detector's config.json ({type(exc).__name__}: {exc})", fix=_INIT_FIX)],
        ) from None
    ours = json.loads(json.dumps(args))  # tuples as the JSON lists config.json holds
    if not isinstance(old_builder, dict):
        old_builder = {}
    problems = []
    for key in sorted(set(ours) | set(old_builder)):
        if key not in old_builder or key not in ours or old_builder[key] != ours[key]:
            theirs = repr(old_builder[key]) if key in old_builder else "no value"
            mine = repr(ours[key]) if key in ours else "no value"
            value = old_builder.get(key)
            value = value if isinstance(value, str) else json.dumps(value, separators=(",", ":"))
            fix = (f"--set detector.{key}={value} to fine-tune this model, or drop --init-from to train from "
                   "detector.weights") if key in old_builder and key in ours else (
                "the model was made by another version of siteloc: drop --init-from to train from detector.weights")
            problems.append(Problem(
                str(cfg_path), f"the model was built with {theirs}, this run builds {mine}", key=f"builder.{key}",
                fix=_BUILDER_FIX.get(key, fix)))
    if old_classes != classes:
        problems.append(Problem(
            str(cfg_path), f"the model detects {old_classes}, the site has {classes}", key="classes",
            fix="fine-tune only on a site with the model's classes, or drop --init-from to train from "
                "detector.weights"))
    if problems:
        raise InputError(f"--init-from {init_dir}: the model is not the network this run trains", problems)
    data = weights_path.read_bytes()
    try:
        state = load_safetensors(data)  # the bytes that were hashed
    except SafetensorError as exc:
        raise InputError(f"--init-from {init_dir}: unreadable weights", [
            Problem(str(weights_path), f"not a safetensors file ({exc})", fix=_INIT_FIX)]) from None
    return {"path": str(init_dir), "weights_sha256": hashlib.sha256(data).hexdigest()}, state


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
