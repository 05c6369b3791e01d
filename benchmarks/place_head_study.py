"""Does a place-trained head on the detector's features beat the paper's IPA? (issue 6's open question)

    .venv/bin/python benchmarks/place_head_study.py --descriptors D --data DATA --model DET [--epochs 30]

D is the output of `siteloc extract`, DATA the ingest it came from, DET the detector it used. Same
database (train stops), queries (test stops and query-run frames) and positives (2 m, 30 deg) as
`siteloc evaluate-retrieval`. The detector's stride-16 map of every image is cached once (average-pooled
to stride 32), then a small head is trained on the database images alone with a multi-positive
contrastive loss over geo-tag pairs (positives within 2 m and 30 deg, negatives beyond 4 m or 60 deg,
temperature 0.07, batches of 64 anchors with one positive each, one-cell shifts and dropout of the map
as augmentation), and its l2-normalised output is searched raw and PCA-whitened:

- gem: 1x1 conv 112 -> 256, ReLU, 3x3 conv, ReLU, GeM (learned p), linear 256;
- grid: the same body (128 channels), 2 x 3 average grid, linear 256;
- vlad: 1x1 conv 112 -> 128, NetVLAD with 16 clusters, linear 256.

The baseline is the first stage of `evaluate-retrieval` (IPA, learned whitening: mAP@4 0.144, R@1 0.204
on office), before RPA re-ranking.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.machine import machine_info  # noqa: E402
from pipeline.retrieval import evaluate as ev  # noqa: E402
from pipeline.retrieval.whitening import PCAWhitening  # noqa: E402


def cached_maps(ex, data: Path, model: Path, images: np.ndarray):
    import torch
    import torch.nn.functional as F

    from pipeline.detection.inference import load_detector, load_image
    from pipeline.progress import progress_bar

    det = load_detector(model, device="cpu")
    maps = None
    with torch.no_grad():
        for k, i in enumerate(progress_bar(images, desc="detector maps", unit="img")):
            batch, _ = det.model.transform([load_image(data / ex.image_ids[i])])
            h, w = batch.image_sizes[0]
            f = det.model.backbone(batch.tensors)["0"][0][:, : (h + 15) // 16, : (w + 15) // 16]
            f = F.avg_pool2d(f[None], 2, ceil_mode=True)[0]
            if maps is None:
                maps = torch.zeros((len(images), *f.shape))
            maps[k] = f
    return maps


def heads(channels: int):
    import torch
    import torch.nn.functional as F
    from torch import nn

    class GeM(nn.Module):
        def __init__(self, hidden=256, out=256):
            super().__init__()
            self.body = nn.Sequential(nn.Conv2d(channels, hidden, 1), nn.ReLU(),
                                      nn.Conv2d(hidden, hidden, 3, padding=1), nn.ReLU())
            self.p = nn.Parameter(torch.tensor(3.0))
            self.fc = nn.Linear(hidden, out)

        def forward(self, x):
            y = self.body(x).clamp(min=1e-6).pow(self.p).mean((2, 3)).pow(1 / self.p)
            return F.normalize(self.fc(y), dim=1)

    class Grid(nn.Module):
        def __init__(self, hidden=128, out=256):
            super().__init__()
            self.body = nn.Sequential(nn.Conv2d(channels, hidden, 1), nn.ReLU(),
                                      nn.Conv2d(hidden, hidden, 3, padding=1), nn.ReLU())
            self.fc = nn.Linear(hidden * 6, out)

        def forward(self, x):
            return F.normalize(self.fc(F.adaptive_avg_pool2d(self.body(x), (2, 3)).flatten(1)), dim=1)

    class VLAD(nn.Module):
        def __init__(self, hidden=128, k=16, out=256):
            super().__init__()
            self.body = nn.Sequential(nn.Conv2d(channels, hidden, 1), nn.ReLU())
            self.assign = nn.Conv2d(hidden, k, 1)
            self.centres = nn.Parameter(torch.randn(k, hidden) * 0.1)
            self.fc = nn.Linear(k * hidden, out)

        def forward(self, x):
            f = F.normalize(self.body(x), dim=1)
            a = self.assign(f).flatten(2).softmax(1)
            f = f.flatten(2)
            v = torch.einsum("bkn,bhn->bkh", a, f) - a.sum(2)[..., None] * self.centres[None]
            v = F.normalize(F.normalize(v, dim=2).flatten(1), dim=1)
            return F.normalize(self.fc(v), dim=1)

    return {"gem": GeM, "grid": Grid, "vlad": VLAD}


def pair_masks(poses: np.ndarray):
    import torch

    d = np.linalg.norm(poses[:, None, :2] - poses[None, :, :2], axis=2)
    t = np.degrees(np.abs(np.angle(np.exp(1j * (poses[:, None, 2] - poses[None, :, 2])))))
    return torch.from_numpy((d <= 2.0) & (t <= 30)), torch.from_numpy((d > 4.0) | (t > 60))


def train_and_measure(name, maps, ndb, db_poses, q_poses, epochs: int, seed: int = 0) -> None:
    import torch
    import torch.nn.functional as F

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = heads(maps.shape[1])[name]()
    opt = torch.optim.Adam(net.parameters(), 1e-3, weight_decay=1e-4)
    pos, neg = pair_masks(db_poses)
    anchors = np.flatnonzero(pos.sum(1) > 1)
    t0 = time.perf_counter()
    for epoch in range(epochs):
        net.train()
        order = rng.permutation(anchors)
        for s in range(0, len(order), 64):
            anc = order[s:s + 64]
            mates = [rng.choice(np.setdiff1d(np.flatnonzero(pos[a]), [a])) for a in anc]
            idx = np.unique(np.concatenate([anc, mates]))
            x = maps[:ndb][idx]
            if rng.random() < 0.5:
                x = torch.roll(x, int(rng.integers(-1, 2)), dims=3)
            e = net(F.dropout(x, 0.1))
            pm, nm = pos[idx][:, idx].clone(), neg[idx][:, idx]
            pm.fill_diagonal_(False)
            logits = (e @ e.T / 0.07).masked_fill(~(pm | nm), -1e9)
            logp = logits - torch.logsumexp(logits, 1, keepdim=True)
            rows = pm.sum(1) > 0
            loss = (-(logp * pm).sum(1)[rows] / pm.sum(1)[rows]).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        if (epoch + 1) % 5 == 0 or epoch + 1 == epochs:
            net.eval()
            with torch.no_grad():
                emb = torch.cat([net(maps[i:i + 256]) for i in range(0, len(maps), 256)]).numpy()
            w = PCAWhitening(None).fit(emb[:ndb])
            searched = (("raw", (emb[ndb:], emb[:ndb])), ("pca", (w.transform(emb[ndb:]), w.transform(emb[:ndb]))))
            for kind, (q, d) in searched:
                m = ev.measure(np.argsort(-(q @ d.T), axis=1)[:, :50], q_poses, db_poses)["2m_30deg"]
                print(f"| {name} | {epoch + 1} | {kind} | {m['map_at_4']:.3f} | {m['recall_at_1']:.3f} | "
                      f"{m['recall_at_4']:.3f} | {m['recall_at_50']:.3f} | {time.perf_counter() - t0:.0f} |",
                      flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--descriptors", type=Path, required=True, help="output of siteloc extract")
    ap.add_argument("--data", type=Path, required=True, help="the ingest it was extracted from")
    ap.add_argument("--model", type=Path, required=True, help="the detector it was extracted with")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--heads", default="gem,grid,vlad")
    args = ap.parse_args()
    for text in machine_info():
        print(text)
    import torch

    torch.set_num_threads(2)
    ex = ev.load_extracted(args.descriptors)
    db, queries = ev.split_database_queries(ex)
    maps = cached_maps(ex, args.data, args.model, np.concatenate([db, queries]))
    print(f"\n{len(db)} database images (training), {len(queries)} queries; positives within 2 m and 30 deg")
    print("| head | epochs | search | mAP@4 | R@1 | R@4 | R@50 | train s |\n|---|---|---|---|---|---|---|---|")
    for name in args.heads.split(","):
        train_and_measure(name, maps, len(db), ex.poses[db], ex.poses[queries], args.epochs)


if __name__ == "__main__":
    main()
