"""Stage `evaluate-detector`: COCO mAP of a trained detector on held-out stops, and a picture of it.

The held-out images are the ingest's `test` split (whole stops the detector never trained or validated
on). Scores come from pycocotools' COCOeval (bbox, all areas, 100 detections per image): mAP@0.5 and
mAP@[.5:.95] overall and per class, per-class AP read from COCOeval's precision array (101-point
interpolated precision, averaged over recall). Outputs: `metrics.json`, `detections.json` (COCO results
format, original pixels, 1-based category ids as in the ingest), `predictions.png` (held-out views with
ground truth dashed and detections above `plot_score` labelled), `config.yaml`, and for DVC
(`pipeline.io.tracked`) `headline.json` (map_50, map_50_95) and `plots/ap_per_class.csv`
(`class,ap_50,ap_50_95`, one row per detector class, empty cells for a class without ground truth).
"""

from __future__ import annotations

import contextlib
import io
import json
import time
from pathlib import Path

import numpy as np

from pipeline.config import SitelocConfig, write_effective_config
from pipeline.errors import InputError, Problem


def coco_map(gt_boxes: list[np.ndarray], gt_labels: list[np.ndarray], det_boxes: list[np.ndarray],
             det_scores: list[np.ndarray], det_labels: list[np.ndarray], classes: list[str]) -> dict:
    """COCO bbox mAP of detections against ground truth, per image lists of x1, y1, x2, y2 boxes.

    Returns {"map_50", "map_50_95", "per_class": {name: {"ap_50", "ap_50_95", "gt"}}}; a class with no
    ground-truth box has None APs and is left out of the means, as COCOeval does.
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images, annotations, results = [], [], []
    for i, (boxes, labels) in enumerate(zip(gt_boxes, gt_labels, strict=True)):
        images.append({"id": i + 1, "width": 1, "height": 1})
        for b, c in zip(np.asarray(boxes, float).reshape(-1, 4), labels, strict=True):
            w, h = b[2] - b[0], b[3] - b[1]
            annotations.append({"id": len(annotations) + 1, "image_id": i + 1, "category_id": int(c),
                                "bbox": [b[0], b[1], w, h], "area": w * h, "iscrowd": 0})
        for b, s, c in zip(np.asarray(det_boxes[i], float).reshape(-1, 4), det_scores[i], det_labels[i], strict=True):
            results.append({"image_id": i + 1, "category_id": int(c), "score": float(s),
                            "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]]})
    gt = COCO()
    gt.dataset = {"images": images, "annotations": annotations,
                  "categories": [{"id": k + 1, "name": n} for k, n in enumerate(classes)]}
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools narrates every step on stdout
        gt.createIndex()
        dt = gt.loadRes(results) if results else COCO()
        ev = COCOeval(gt, dt, "bbox")
        ev.evaluate()
        ev.accumulate()
    precision = ev.eval["precision"]  # (iou thresholds, recall points, classes, areas, max dets)
    counts = np.bincount(np.concatenate([np.asarray(lb, int) for lb in gt_labels] + [np.zeros(0, int)]),
                         minlength=len(classes) + 1)
    per_class = {}
    for k, name in enumerate(classes):
        p = precision[:, :, k, 0, -1]
        has_gt = counts[k + 1] > 0
        per_class[name] = {
            "ap_50": float(np.mean(np.maximum(p[0], 0))) if has_gt else None,
            "ap_50_95": float(np.mean(np.maximum(p, 0))) if has_gt else None,
            "gt": int(counts[k + 1]),
        }
    scored = [v for v in per_class.values() if v["ap_50"] is not None]
    return {"map_50": float(np.mean([v["ap_50"] for v in scored])) if scored else None,
            "map_50_95": float(np.mean([v["ap_50_95"] for v in scored])) if scored else None,
            "per_class": per_class}


def run_evaluate_detector(cfg: SitelocConfig, *, inputs: dict[str, Path], outputs: dict[str, Path],
                          force: bool = False, progress: bool = True) -> Path:
    from pipeline.detection.data import load_samples
    from pipeline.detection.inference import detector_features, load_detector, load_image
    from pipeline.io.atomic import atomic_dir, check_output, write_text_atomic
    from pipeline.io.tracked import write_headline, write_plot_table
    from pipeline.progress import progress_bar

    d = cfg.detector
    out = Path(outputs["out"])
    check_output(out, force=force, inputs=inputs.values())
    det = load_detector(Path(inputs["model"]), device=d.device)
    det.model.roi_heads.nms_thresh = d.box_nms_thresh  # a test-time setting: the config's, not the training run's
    _, splits, classes = load_samples(Path(inputs["data"]))
    if classes != det.classes:
        raise InputError(f"{inputs['data']}: its classes differ from the detector's",
                         [Problem(str(inputs["model"]), f"detector classes {det.classes}, site classes {classes}",
                                  fix="evaluate on the site the detector was trained for")])
    samples = splits.get(d.eval_split, [])
    if not samples:
        raise InputError(f"{inputs['data']}: no '{d.eval_split}' images to evaluate on",
                         [Problem(str(Path(inputs["data"]) / "images.parquet"), f"split '{d.eval_split}' is empty",
                                  fix="ingest with a test share (ingest.split.test_fraction) or set "
                                      "detector.eval_split")])
    found = []
    t0 = time.perf_counter()
    bar = progress_bar(total=len(samples), desc="detecting", unit="img", enabled=progress)
    for i in range(0, len(samples), d.eval_batch):
        chunk = samples[i:i + d.eval_batch]
        found.extend(detector_features(det, [load_image(s.path) for s in chunk]))
        bar.update(len(chunk))
    bar.close()
    seconds = time.perf_counter() - t0
    scores = coco_map([s.boxes for s in samples], [s.labels for s in samples], [f.boxes for f in found],
                      [f.scores for f in found], [f.labels for f in found], classes)
    detections = [{"image_id": s.image_id, "category_id": int(c), "score": round(float(sc), 5),
                   "bbox": [round(float(v), 2) for v in (b[0], b[1], b[2] - b[0], b[3] - b[1])]}
                  for s, f in zip(samples, found, strict=True)
                  for b, sc, c in zip(f.boxes, f.scores, f.labels, strict=True)]
    metrics = {"split": d.eval_split, "images": len(samples), "stops": len({s.stop_id for s in samples}),
               "backbone": det.config["builder"]["backbone"], **scores,
               "images_per_s": round(len(samples) / max(seconds, 1e-9), 3), "device": str(det.device),
               "box_nms_thresh": d.box_nms_thresh}
    with atomic_dir(out, force=force, inputs=inputs.values()) as tmp:
        write_text_atomic(tmp / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        write_headline(tmp, {"map_50": scores["map_50"], "map_50_95": scores["map_50_95"]})
        write_plot_table(tmp, "ap_per_class", ["class", "ap_50", "ap_50_95"],
                         [(name, v["ap_50"], v["ap_50_95"]) for name, v in scores["per_class"].items()])
        write_text_atomic(tmp / "detections.json", json.dumps(detections) + "\n")
        predictions_figure(tmp / "predictions.png", samples, found, classes, d.plot_score, d.plot_images,
                           title=f"{metrics['backbone']} on held-out stops: mAP@0.5 {_fmt(scores['map_50'])}, "
                                 f"mAP@[.5:.95] {_fmt(scores['map_50_95'])}")
        write_effective_config(cfg, tmp, stage="evaluate-detector", inputs=inputs)
    return out


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def predictions_figure(path: Path, samples, found, classes: list[str], min_score: float, n: int, *,
                       title: str) -> Path:
    """A grid of held-out views (evenly spread over the split): ground truth dashed, detections labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.evaluation.plots import save_figure
    from pipeline.io.images import open_image

    picks = np.unique(np.linspace(0, len(samples) - 1, min(n, len(samples))).round().astype(int))
    cols = min(4, len(picks))
    rows = -(-len(picks) // cols)
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, k in zip(axes.ravel(), picks, strict=False):  # the last row may have empty axes
        s, f = samples[k], found[k]
        ax.imshow(open_image(s.path))
        for b in s.boxes:
            ax.add_patch(plt.Rectangle(b[:2], b[2] - b[0], b[3] - b[1], fill=False, ls="--", lw=1.0,
                                       ec="white"))
        for b, sc, c in zip(f.boxes, f.scores, f.labels, strict=True):
            if sc < min_score:
                continue
            col = colours((int(c) - 1) % 10)
            ax.add_patch(plt.Rectangle(b[:2], b[2] - b[0], b[3] - b[1], fill=False, lw=1.6, ec=col))
            ax.text(b[0], b[1], f"{classes[int(c) - 1]} {sc:.2f}", fontsize=6, color="white", va="bottom",
                    bbox={"facecolor": col, "pad": 1, "lw": 0})
        ax.set_title(s.image_id.split("/")[-1], fontsize=7)
    fig.suptitle(f"{title}\nwhite dashed: ground truth; coloured: detections with score >= {min_score}",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)
