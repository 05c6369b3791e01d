"""Boxes from the instance buffer agree with a brute-force scan of the buffer."""

from __future__ import annotations

import numpy as np

from pipeline.sitegen.boxes import instance_boxes


def test_instance_boxes_match_brute_force():
    rng = np.random.default_rng(0)
    ids = np.zeros((60, 80), dtype=np.uint32)
    for iid in range(1, 8):
        y, x = rng.integers(0, 50), rng.integers(0, 70)
        h, w = rng.integers(1, 10), rng.integers(1, 10)
        ids[y : y + h, x : x + w] = iid
    ids[rng.random(ids.shape) < 0.02] = 9  # scattered pixels of one more instance
    got = instance_boxes(ids)
    for iid in np.unique(ids[ids > 0]):
        ys, xs = np.nonzero(ids == iid)
        assert got[int(iid)] == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1, len(xs))
    assert set(got) == set(int(i) for i in np.unique(ids[ids > 0]))
    assert instance_boxes(np.zeros((4, 4), dtype=np.uint32)) == {}
