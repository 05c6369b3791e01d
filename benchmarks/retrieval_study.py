"""What limits retrieval on a site: other global descriptors, SIFT verification, and where the misses land.

    .venv/bin/python benchmarks/retrieval_study.py --descriptors D --data DATA --model DET [--sift 150]
    .venv/bin/python benchmarks/retrieval_study.py --descriptors D --data DATA --sift 300 --sift-only

D is the output of `siteloc extract`, DATA the ingest it came from, DET the detector it used. Same
database / queries / positives (2 m, 30 deg) as `siteloc evaluate-retrieval`.

1. Global descriptors, IPA Top-50 and after RPA re-ranking (the extraction's regions, PCA-whitened):
   sum (the paper's IPA), GeM (p = 3), MAC and 2 x 2 grid pooling of the detector's stride-16 map and of
   the ImageNet EfficientNet-Lite0's stride-16 and stride-32 maps at full resolution; each PCA- or
   learned-whitened. One pass over every image (about 3 images/s on 2 cores).
2. Where the Top-1 after re-ranking lands (distance and heading from the query), per query source.
3. With `--sift N`: N sampled queries re-ranked by the RANSAC inliers of RootSIFT matches (OpenCV) between
   the query and each of its IPA Top-50 (classic spatial verification), against the same queries' RPA order:
   inliers of a fundamental matrix (any scene) and of a homography (a poster, a plate, a wall). With
   `--sift-only`, steps 1-2 are skipped and the IPA Top-50 is the extraction's own (as `evaluate-retrieval`
   ranks it, PCA-whitened), so no detector is run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.config import SitelocConfig  # noqa: E402
from pipeline.machine import machine_info  # noqa: E402
from pipeline.retrieval import evaluate as ev  # noqa: E402
from pipeline.retrieval.metrics import positives  # noqa: E402
from pipeline.retrieval.whitening import LearnedWhitening, PCAWhitening, geo_pairs  # noqa: E402

POOLS = ("sum", "gem", "mac", "grid2")


def pooled(fmap) -> dict[str, np.ndarray]:
    import torch
    import torch.nn.functional as F

    c, h, w = fmap.shape
    cells = [F.normalize(fmap[:, i * h // 2:(i + 1) * h // 2, j * w // 2:(j + 1) * w // 2].sum((1, 2)), dim=0)
             for i in range(2) for j in range(2)]
    out = {"sum": fmap.sum((1, 2)), "mac": fmap.amax((1, 2)),
           "gem": fmap.clamp(min=1e-6).pow(3).mean((1, 2)).pow(1 / 3), "grid2": torch.cat(cells)}
    return {k: F.normalize(v, dim=0).numpy() for k, v in out.items()}


def global_descriptors(ex: ev.Extracted, data: Path, model: Path) -> dict[str, np.ndarray]:
    import torch

    from pipeline.detection.efficientnet_lite import EfficientNetLite0, load_imagenet_weights
    from pipeline.detection.inference import load_detector, load_image
    from pipeline.progress import progress_bar

    det = load_detector(model, device="cpu")
    net = EfficientNetLite0()
    load_imagenet_weights(net)
    net.eval()
    mean, std = (torch.tensor(v).view(3, 1, 1) for v in (EfficientNetLite0.MEAN, EfficientNetLite0.STD))
    found: dict[str, list] = {}
    with torch.no_grad():
        for image_id in progress_bar(ex.image_ids, desc="global descriptors", unit="img"):
            im = load_image(data / image_id)
            batch, _ = det.model.transform([im])
            maps = {"detector s16": det.model.backbone(batch.tensors)["0"][0]}
            feats = net.features(((im - mean) / std)[None])
            maps["imagenet s16"], maps["imagenet s32"] = feats[16][0], feats[32][0]
            for name, fmap in maps.items():
                for pool, v in pooled(fmap).items():
                    found.setdefault(f"{name} {pool}", []).append(v)
    return {k: np.stack(v) for k, v in found.items()}


def rpa_rerank(ex, db, queries, first, cfg) -> np.ndarray:
    _, w_rpa = ev.fit_whitenings(ex, db, "pca", cfg)
    rpa = w_rpa.transform(ex.rpa)
    out = np.empty_like(first)
    for k, q in enumerate(queries):
        regions = rpa[ev.query_regions(ex, q, cfg.query_regions)]
        scores = [np.max(regions @ rpa[ex.offsets[db[j]]:ex.offsets[db[j] + 1]].T, axis=1).mean() for j in first[k]]
        out[k] = first[k][np.argsort(-np.asarray(scores), kind="stable")]
    return out


def line(name: str, ranked, ex, db, queries) -> str:
    m = ev.measure(ranked, ex.poses[queries], ex.poses[db])["2m_30deg"]
    return (f"| {name} | {m['map_at_4']:.3f} | {m['recall_at_1']:.3f} | {m['recall_at_4']:.3f} | "
            f"{m['recall_at_10']:.3f} | {m['recall_at_50']:.3f} |")


def where_top1_lands(ranked, ex, db, queries) -> None:
    q, t = ex.poses[queries], ex.poses[db][ranked[:, 0]]
    dist = np.linalg.norm(q[:, :2] - t[:, :2], axis=1)
    turn = np.degrees(np.abs(np.angle(np.exp(1j * (q[:, 2] - t[:, 2])))))
    print("\nwhere the Top-1 (IPA + RPA, learned whitening) lands: share of queries")
    print("| distance | all | heading within 30 deg | heading over 90 deg |\n|---|---|---|---|")
    for lo, hi in ((0, 2), (2, 5), (5, 10), (10, np.inf)):
        s = (dist >= lo) & (dist < hi)
        print(f"| {lo}-{hi} m | {s.mean():.3f} | {(s & (turn <= 30)).mean():.3f} | {(s & (turn > 90)).mean():.3f} |")
    good = (dist <= 2) & (turn <= 30)
    for source in np.unique(ex.splits[queries]):
        m = ex.splits[queries] == source
        print(f"- {source}: {m.sum()} queries, Top-1 correct {good[m].mean():.3f}")


def sift_verification(ex, db, queries, first, reranked, data: Path, n: int, label: str) -> None:
    import cv2

    sift, matcher = cv2.SIFT_create(nfeatures=800), cv2.BFMatcher(cv2.NORM_L2)
    cache: dict[int, tuple] = {}

    def features(i: int):
        if i not in cache:
            kp, des = sift.detectAndCompute(cv2.imread(str(data / ex.image_ids[i]), cv2.IMREAD_GRAYSCALE), None)
            des = np.zeros((0, 128), np.float32) if des is None else des
            cache[i] = (np.float32([k.pt for k in kp]), np.sqrt(des / (des.sum(1, keepdims=True) + 1e-7)))
        return cache[i]

    def inliers(a: int, b: int) -> tuple[int, int]:
        """RANSAC inliers of a fundamental matrix and of a homography between images a and b."""
        (pa, da), (pb, dbb) = features(a), features(b)
        if len(da) < 8 or len(dbb) < 8:
            return 0, 0
        good = [m[0] for m in matcher.knnMatch(da, dbb, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        if len(good) < 8:
            return 0, 0
        src, dst = pa[[g.queryIdx for g in good]], pb[[g.trainIdx for g in good]]
        counts = []
        for fit in (lambda: cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, 2.0, 0.999, 2000)[1],
                    lambda: cv2.findHomography(src, dst, cv2.RANSAC, 4.0, maxIters=2000, confidence=0.999)[1]):
            try:
                mask = fit()
            except cv2.error:
                mask = None
            counts.append(0 if mask is None else int(mask.sum()))
        return counts[0], counts[1]

    pick = np.sort(np.random.default_rng(0).choice(len(queries), min(n, len(queries)), replace=False))
    t0 = time.perf_counter()
    counts = np.array([[inliers(int(queries[k]), int(db[j])) for j in first[k]] for k in pick])
    ms = 1e3 * (time.perf_counter() - t0) / len(pick)
    print(f"\nSIFT verification on {len(pick)} sampled queries ({ms:.0f} ms a query, features included):")
    print("| order | mAP@4 | R@1 | R@4 | R@10 | R@50 |\n|---|---|---|---|---|---|")
    orders = [(f"IPA ({label})", first[pick]), ("+ RPA", reranked[pick])]
    for c, model in enumerate(("fundamental matrix", "homography")):
        order = np.argsort(-counts[:, :, c], axis=1, kind="stable")
        orders.append((f"+ SIFT inliers, {model}", np.take_along_axis(first[pick], order, axis=1)))
    for name, ranked in orders:
        print(line(name, ranked, ex, db, queries[pick]))
    # Where the homography order's wrong Top-1s land, and how much the best candidate matched at all.
    qp, top1 = ex.poses[queries[pick]], orders[-1][1][:, 0]
    pos = positives(qp, ex.poses[db], *ev.MAIN)
    hit = pos[np.arange(len(pick)), top1]
    miss = ~hit & pos.any(axis=1)
    dist = np.linalg.norm(qp[:, :2] - ex.poses[db[top1], :2], axis=1)[miss]
    best = counts[:, :, 1].max(axis=1)
    print(f"\nHomography order: {miss.sum()} of {pos.any(axis=1).sum()} Top-1s wrong; of those, "
          f"{np.mean(dist <= 2):.2f} within 2 m (another heading), {np.mean((dist > 2) & (dist <= 10)):.2f} at "
          f"2-10 m, {np.mean(dist > 10):.2f} beyond 10 m. Best candidate's inliers, median: right Top-1 "
          f"{np.median(best[hit]):.0f}, wrong {np.median(best[miss]):.0f}; under 15: right "
          f"{np.mean(best[hit] < 15):.2f}, wrong {np.mean(best[miss] < 15):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--descriptors", type=Path, required=True, help="output of siteloc extract")
    ap.add_argument("--data", type=Path, required=True, help="the ingest it was extracted from")
    ap.add_argument("--model", type=Path, help="the detector it was extracted with (not with --sift-only)")
    ap.add_argument("--sift", type=int, default=0, help="queries to verify with SIFT (0: skip)")
    ap.add_argument("--sift-only", action="store_true", help="only the SIFT verification of the extraction's "
                    "own IPA Top-50, PCA-whitened (no detector run)")
    args = ap.parse_args()
    if not args.sift_only and args.model is None:
        ap.error("--model is required unless --sift-only")
    for text in machine_info():
        print(text)
    cfg = SitelocConfig().retrieval
    ex = ev.load_extracted(args.descriptors)
    db, queries = ev.split_database_queries(ex)
    if args.sift_only:
        ranked = ev.rank_all(ex, db, ex, queries, "pca", cfg)
        print(f"\n{len(db)} database images, {len(queries)} queries; positives within 2 m and 30 deg")
        sift_verification(ex, db, queries, ranked["ipa"], ranked["ipa+rpa"], args.data, args.sift or 150, "PCA")
        return
    pairs = geo_pairs(ex.poses[db, :2], ex.poses[db, 2], ex.groups[db], max_distance=cfg.pair_distance,
                      max_heading_deg=cfg.pair_heading_deg)
    found = global_descriptors(ex, args.data, args.model)
    print(f"\n{len(db)} database images, {len(queries)} queries; positives within 2 m and 30 deg")
    print("| descriptor | mAP@4 | R@1 | R@4 | R@10 | R@50 |\n|---|---|---|---|---|---|")
    keep = {}
    for name, x in found.items():
        for kind in ("pca", "learned"):
            w = PCAWhitening(None).fit(x[db]) if kind == "pca" else LearnedWhitening(None).fit(x[db], pairs)
            first = np.argsort(-(w.transform(x[queries]) @ w.transform(x[db]).T), axis=1)[:, :cfg.top_n]
            reranked = rpa_rerank(ex, db, queries, first, cfg)
            print(line(f"{name} ({x.shape[1]}-d), {kind}", first, ex, db, queries))
            print(line(f"{name} ({x.shape[1]}-d), {kind} + RPA", reranked, ex, db, queries), flush=True)
            if name == "detector s16 sum" and kind == "learned":
                keep = {"first": first, "reranked": reranked}
    where_top1_lands(keep["reranked"], ex, db, queries)
    if args.sift:
        sift_verification(ex, db, queries, keep["first"], keep["reranked"], args.data, args.sift, "learned")


if __name__ == "__main__":
    main()
