"""Stage `train-place`: a place-recognition network trained on the site's own geo-tagged images.

An ImageNet trunk (`place.trunk`) gets a NetVLAD or GeM head (`pipeline.retrieval.place_heads`); the head
and the trunk's last `place.tune_blocks` blocks learn, by the triplet loss of NetVLAD (Arandjelovic et al.
2016: margin on squared distances, the best-matching positive, hard negatives re-mined from every
image's current descriptor each epoch), from the database views and mapping-run frames
(`pipeline.retrieval.place_data`). The frozen part of the trunk runs once per image and is cached, so
only the trainable tail runs per step: the head alone (the default) trains in minutes on a CPU, a tuned
block wants a GPU. NetVLAD's clusters start from k-means of the
site's local features. The epoch kept is the one with the best recall@1 of the held-out mapping run.

Writes place.safetensors (what `retrieval.backbone: checkpoint` loads), metrics.json, headline.json,
plots/training.csv, training.png, config.yaml. Checkpoints after every epoch; an interrupted training
resumes when rerun.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem


def split_trunk(trunk, tail: int):
    """(frozen prefix, trainable tail) of a backbone's trunk, sharing its modules: the last `tail` MBConv
    blocks of Lite0, or the last `tail` conv layers of VGG16 (with the ReLUs and pools after them)."""
    from torch import nn

    if hasattr(trunk, "_blocks"):
        blocks = list(trunk._blocks)
        if tail > len(blocks):
            raise ValueError(f"place.tune_blocks={tail}: this trunk has {len(blocks)} blocks")
        head = [trunk._conv_stem, trunk._bn0, nn.ReLU6()]
        return nn.Sequential(*head, *blocks[:len(blocks) - tail]), nn.Sequential(*blocks[len(blocks) - tail:])
    layers = list(trunk.features)
    convs = [i for i, m in enumerate(layers) if isinstance(m, nn.Conv2d)]
    if tail > len(convs):
        raise ValueError(f"place.tune_blocks={tail}: this trunk has {len(convs)} conv layers")
    cut = convs[len(convs) - tail] if tail else len(layers)
    return nn.Sequential(*layers[:cut]), nn.Sequential(*layers[cut:])


def cache_prefix(bb, prefix, paths: list[Path], device, *, progress: bool) -> list:
    """The frozen prefix's output of every image (float16, on `device`)."""
    import torch

    from pipeline.detection.inference import load_image
    from pipeline.progress import progress_bar

    out = []
    with torch.no_grad():
        for p in progress_bar(paths, desc="caching frozen trunk", unit="img", enabled=progress):
            x = load_image(p)[None].to(device)
            out.append(prefix((x - bb.mean) / bb.std)[0].to(torch.float16))
    return out


def forward(tail, head, cache: list, idx) -> torch.Tensor:  # noqa: F821
    """Global descriptors of the cached images `idx` (images of one size go through together)."""
    import torch

    by_shape: dict[tuple, list[int]] = {}
    for k, i in enumerate(idx):
        by_shape.setdefault(tuple(cache[i].shape), []).append(k)
    parts, order = [], []
    for ks in by_shape.values():
        parts.append(head(tail(torch.stack([cache[idx[k]] for k in ks]).float())))
        order.extend(ks)
    out = torch.cat(parts)
    return out[torch.as_tensor(np.argsort(order), device=out.device)]


def describe_all(tail, head, cache: list, batch: int = 32) -> np.ndarray:
    import torch

    with torch.no_grad():
        return np.concatenate([forward(tail, head, cache, list(range(i, min(i + batch, len(cache)))))
                               .float().cpu().numpy() for i in range(0, len(cache), batch)])


def init_netvlad(head, tail, cache: list, *, seed: int, samples: int = 20000) -> None:
    """Clusters from k-means of the site's (l2-normalised) local features; assignment sharpness alpha such
    that a feature's best cluster outweighs its second by 100:1 on average (the NetVLAD authors' init)."""
    import torch
    import torch.nn.functional as F
    from sklearn.cluster import KMeans

    rng = np.random.default_rng(seed)
    picks = rng.choice(len(cache), size=min(len(cache), 200), replace=False)
    with torch.no_grad():
        feats = [F.normalize(tail(cache[i][None].float()), dim=1)[0].flatten(1).T.cpu().numpy() for i in picks]
    x = np.concatenate(feats)
    x = x[rng.choice(len(x), size=min(len(x), samples), replace=False)]
    km = KMeans(head.clusters, n_init=1, random_state=seed).fit(x)
    centres = km.cluster_centers_.astype(np.float32)
    unit = centres / np.maximum(np.linalg.norm(centres, axis=1, keepdims=True), 1e-12)
    dots = np.sort(x @ unit.T, axis=1)[:, ::-1]
    gap = float(np.mean(dots[:, 0] - dots[:, 1])) if head.clusters > 1 else 1.0
    alpha = -np.log(0.01) / max(gap, 1e-6)
    dev = head.centroids.device
    with torch.no_grad():
        head.centroids.copy_(torch.from_numpy(centres).to(dev))
        head.assign.weight.copy_(torch.from_numpy(alpha * unit)[:, :, None, None].to(dev))
        head.assign.bias.zero_()


def validation_scores(desc: np.ndarray, poses: np.ndarray, queries: np.ndarray, database: np.ndarray, cfg) -> dict:
    """Recall@1 and mAP@4 of the held-out frames against the database views (positives: the evaluation's)."""
    from pipeline.retrieval.metrics import map_at, positives, recall_at, relevance

    if not len(queries):
        return {}
    ranked = np.argsort(-(desc[queries] @ desc[database].T), axis=1, kind="stable")[:, :10]
    pos = positives(poses[queries], poses[database], cfg.positive_m, cfg.positive_heading_deg)
    rel = relevance(ranked, pos)
    has = pos.any(axis=1)
    return {"recall_at_1": recall_at(rel, has, 1), "recall_at_10": recall_at(rel, has, 10),
            "map_at_4": map_at(rel, pos, 4), "queries": int(has.sum())}


def _fingerprint(cfg, ims, trunk_sha: str | None) -> str:
    h = hashlib.sha256(json.dumps({"place": cfg.model_dump(mode="json"), "trunk": trunk_sha}, sort_keys=True).encode())
    for i, p in zip(ims.ids, ims.poses.round(6).tolist(), strict=True):
        h.update(f"{i}{p}".encode())
    return h.hexdigest()


def run_train_place(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path], force: bool = False,
                    progress: bool = True) -> Path:
    import torch

    from pipeline.detection.inference import pick_device
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.io.checkpoint import resume_state
    from pipeline.io.checkpoint import save_checkpoint as save_state
    from pipeline.progress import progress_bar
    from pipeline.retrieval.backbones import assemble, load_backbone, save_checkpoint
    from pipeline.retrieval.place_data import mine, pair_sets, place_images

    c = cfg.place
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    data = Path(inputs["data"])
    ims = place_images(data, frame_stride=c.frame_stride, validation_run=c.validation_run)
    train = np.flatnonzero(~ims.validation)
    pairs = pair_sets(ims.poses[train], ims.group[train], positive_m=c.positive_m,
                      positive_heading_deg=c.positive_heading_deg, negative_m=c.negative_m,
                      negative_heading_deg=c.negative_heading_deg, min_negatives=c.hard_pool)
    if len(pairs.anchors) < c.batch:
        raise InputError(f"{data}: {len(pairs.anchors)} training images have a positive (within {c.positive_m} m and "
                         f"{c.positive_heading_deg} deg, from another stop or run) and {c.hard_pool} negatives",
                         [Problem(str(data), f"{len(train)} training images", fix=(
                             "ingest more stops or mapping-run frames, lower place.frame_stride, or widen "
                             "place.positive_m / place.positive_heading_deg"))])
    torch.manual_seed(c.seed)
    rng = np.random.default_rng(c.seed)
    device = pick_device(c.device)
    trunk = load_backbone(c.trunk, c.trunk_weights)
    bb = assemble(c.trunk, c.head, clusters=c.clusters, mean=trunk.mean.flatten().tolist(),
                  std=trunk.std.flatten().tolist())
    bb.trunk.load_state_dict(trunk.trunk.state_dict())
    bb.to(device).eval()  # batch norm stays frozen (its statistics are ImageNet's); gradients still flow
    prefix, tail = split_trunk(bb.trunk, c.tune_blocks)
    for p in prefix.parameters():
        p.requires_grad_(False)
    t0 = time.perf_counter()
    cache = cache_prefix(bb, prefix, ims.paths, device, progress=progress)
    cache_s = time.perf_counter() - t0
    partial = out.with_name(out.name + ".partial")
    ckpt_path = partial / "checkpoint.pt"
    fingerprint = _fingerprint(c, ims, trunk.weights_sha256)
    ckpt = resume_state(ckpt_path, fingerprint, force=force, what="other place settings or images")
    if ckpt is None and c.head == "netvlad":
        init_netvlad(bb.head, tail, [cache[i] for i in train], seed=c.seed)
    params = [{"params": [p for p in tail.parameters()], "lr": c.lr},
              {"params": list(bb.head.parameters()), "lr": c.head_lr}]
    opt = torch.optim.Adam([g for g in params if g["params"]])
    start, history, best = 0, [], None
    if ckpt is not None:
        bb.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        start, history = int(ckpt["epoch"]), json.loads(ckpt["history"])
        best = (tuple(json.loads(ckpt["best_score"])), ckpt["best_model"])
        rng = np.random.default_rng(int(ckpt["rng_seed"]))
        torch.set_rng_state(ckpt["torch_rng"])
    queries, database = np.flatnonzero(ims.validation), np.flatnonzero(ims.database)

    def score(desc):
        v = validation_scores(desc, ims.poses, queries, database, c)
        return v, (v.get("recall_at_1", 0.0), v.get("map_at_4", 0.0))

    if start == 0:
        desc = describe_all(tail, bb.head, cache)
        v, key = score(desc)
        history.append({"epoch": 0, "loss": None, "validation": v})
        best = (key, {k: t.detach().cpu().clone() for k, t in bb.state_dict().items()})
    t1 = time.perf_counter()
    for epoch in range(start, c.epochs):
        desc = describe_all(tail, bb.head, [cache[i] for i in train])
        pos, neg = mine(desc @ desc.T, pairs, pairs.anchors, negatives=c.negatives, hard_pool=c.hard_pool, rng=rng)
        order = rng.permutation(len(pairs.anchors))
        total, active = 0.0, 0.0
        for i in progress_bar(range(0, len(order), c.batch), desc=f"training place network, epoch {epoch + 1}/"
                              f"{c.epochs}", unit="step", enabled=progress):
            b = order[i:i + c.batch]
            members = np.unique(np.concatenate([pairs.anchors[b], pos[b], neg[b].ravel()]))
            d = forward(tail, bb.head, cache, train[members].tolist())
            a, p_, n_ = (d[torch.as_tensor(np.searchsorted(members, ix), device=d.device)]  # rows of `members`
                         for ix in (pairs.anchors[b], pos[b], neg[b]))
            dp = ((a - p_) ** 2).sum(1)
            dn = ((a[:, None] - n_) ** 2).sum(2)
            hinge = torch.relu(c.margin + dp[:, None] - dn)
            loss = hinge.mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(b)
            active += float((hinge > 0).float().mean()) * len(b)
        v, key = score(describe_all(tail, bb.head, cache))
        history.append({"epoch": epoch + 1, "loss": total / len(order), "active_triplets": active / len(order),
                        "validation": v})
        if not len(queries) or key > best[0]:
            best = (key, {k: t.detach().cpu().clone() for k, t in bb.state_dict().items()})
        partial.mkdir(parents=True, exist_ok=True)
        seed_next = int(rng.integers(0, 2**31))
        rng = np.random.default_rng(seed_next)
        save_state(ckpt_path, {"model": bb.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch + 1,
                               "history": json.dumps(history), "best_score": json.dumps(list(best[0])),
                               "best_model": best[1], "rng_seed": seed_next, "torch_rng": torch.get_rng_state()},
                   fingerprint)
    train_s = time.perf_counter() - t1
    bb.load_state_dict(best[1])
    bb.cpu().eval()
    kept = max(history, key=lambda h: (h["validation"].get("recall_at_1", 0.0), h["validation"].get("map_at_4", 0.0))
               ) if len(queries) else history[-1]
    metrics = {"images": len(ims), "database_views": int(ims.database.sum()), "run_frames": int((~ims.database).sum()),
               "validation_frames": int(len(queries)), "anchors": int(len(pairs.anchors)),
               "trainable_parameters": int(sum(p.numel() for g in params for p in g["params"])),
               "descriptor_dim": int(bb.dim), "device": str(device), "trunk_weights": trunk.source,
               "cache_seconds": round(cache_s, 1), "train_seconds": round(train_s, 1),
               "kept_epoch": kept["epoch"], "history": history}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        save_checkpoint(bb, tmp / "place.safetensors")
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        training_figure(tmp / "training.png", history, kept["epoch"])
        write_tracked(tmp, metrics)
        write_effective_config(cfg, tmp, stage="train-place", inputs=inputs)
    if ckpt_path.exists():
        ckpt_path.unlink()
        partial.rmdir()
    return out


def write_tracked(out: Path, metrics: dict) -> None:
    """headline.json (the kept epoch's held-out recall@1 and mAP@4; None without a held-out run) and
    plots/training.csv (epoch, loss, held-out recall@1, mAP@4; epoch 0: before training)."""
    from pipeline.io.tracked import write_headline, write_plot_table

    kept = next(h for h in metrics["history"] if h["epoch"] == metrics["kept_epoch"])["validation"]
    write_headline(out, {"held_out_recall_at_1": kept.get("recall_at_1"), "held_out_map_at_4": kept.get("map_at_4")})
    write_plot_table(out, "training", ["epoch", "loss", "recall_at_1", "map_at_4"],
                     [(h["epoch"], h["loss"], h["validation"].get("recall_at_1"), h["validation"].get("map_at_4"))
                      for h in metrics["history"]])


def training_figure(path: Path, history: list[dict], kept: int | None = None) -> Path:
    """Loss and held-out recall@1 / mAP@4 per epoch; a dashed line at the epoch kept."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.io.atomic import atomic_file

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.2))
    loss = [(h["epoch"], h["loss"]) for h in history if h["loss"] is not None]
    if loss:
        ax1.plot(*zip(*loss, strict=True), "o-")
    ax1.set(xlabel="epoch", ylabel="triplet loss", title="training")
    for key, label in (("recall_at_1", "recall@1"), ("map_at_4", "mAP@4")):
        pts = [(h["epoch"], h["validation"][key]) for h in history if key in h["validation"]]
        if pts:
            ax2.plot(*zip(*pts, strict=True), "o-", label=label)
    ax2.set(xlabel="epoch", ylabel="held-out mapping run", title="validation (epoch 0: before training)", ylim=(0, 1))
    if kept is not None:
        ax2.axvline(kept, color="grey", linestyle="--", label=f"kept (epoch {kept})")
    if ax2.lines:
        ax2.legend()
    fig.tight_layout()
    with atomic_file(Path(path), "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)
    return Path(path)
