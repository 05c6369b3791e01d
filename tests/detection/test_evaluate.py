"""COCO mAP wiring checked on hand-computed cases (101-point interpolated precision)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.detection.evaluate import coco_map

CLASSES = ["door", "chair", "plant"]
A = np.array([[10.0, 10.0, 110.0, 110.0]])
B = np.array([[200.0, 50.0, 260.0, 170.0]])


def _run(gt, det):
    return coco_map([g[0] for g in gt], [np.array(g[1]) for g in gt], [d[0] for d in det],
                    [np.array(d[1]) for d in det], [np.array(d[2]) for d in det], CLASSES)


def test_perfect_detections_score_one_and_absent_classes_are_left_out():
    gt = [(np.vstack([A, B]), [1, 2]), (A, [2])]
    det = [(np.vstack([A, B]), [0.9, 0.8], [1, 2]), (A, [0.7], [2])]
    m = _run(gt, det)
    assert m["map_50"] == pytest.approx(1.0) and m["map_50_95"] == pytest.approx(1.0)
    assert m["per_class"]["plant"] == {"ap_50": None, "ap_50_95": None, "gt": 0}
    assert m["per_class"]["chair"]["gt"] == 2


def test_half_recall_gives_51_of_101_recall_points():
    gt = [(A, [1]), (A, [1])]
    det = [(A, [0.9], [1]), (np.zeros((0, 4)), [], [])]
    assert _run(gt, det)["per_class"]["door"]["ap_50"] == pytest.approx(51 / 101)


def test_iou_062_counts_at_050_055_060_only():
    det_box = np.array([[10.0, 10.0, 110.0, 72.0]])  # IoU with A: 62 / 100
    m = _run([(A, [1])], [(det_box, [0.9], [1])])
    assert m["per_class"]["door"]["ap_50"] == pytest.approx(1.0)
    assert m["per_class"]["door"]["ap_50_95"] == pytest.approx(3 / 10)


def test_a_higher_scored_false_positive_halves_precision():
    det = [(np.vstack([B, A]), [0.9, 0.8], [1, 1])]  # B is not a door here: a false positive ranked first
    assert _run([(A, [1])], det)["per_class"]["door"]["ap_50"] == pytest.approx(0.5)


def test_wrong_class_is_a_miss():
    m = _run([(A, [1])], [(A, [0.9], [2])])
    assert m["per_class"]["door"]["ap_50"] == 0.0 and m["map_50"] == 0.0
