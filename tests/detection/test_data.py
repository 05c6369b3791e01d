"""Detection samples from an ingested site: boxes to pixels and back, stop-wise splits, flips that mirror boxes."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.detection.data import DetectionDataset, load_samples, split_by_stop, to_original
from pipeline.ingest import run_ingest
from tests.fixtures.capture_site import write_capture_site


@pytest.fixture(scope="module")
def ingested(tmp_path_factory):
    root = tmp_path_factory.mktemp("det")
    site = write_capture_site(root / "site")
    return run_ingest(load_config("ci"), inputs={"site": site}, outputs={"out": root / "ing"}, progress=False)


def test_samples_carry_the_ingested_boxes(ingested):
    samples, splits, classes = load_samples(ingested)
    assert len(classes) >= 1 and set(splits) <= {"train", "test"}
    with_boxes = [s for s in samples if len(s.boxes)]
    assert with_boxes and all(s.labels.min() >= 1 and s.labels.max() <= len(classes) for s in with_boxes)
    assert all(s.path.is_file() for s in samples)


def test_split_by_stop_keeps_stops_whole_and_is_seeded(ingested):
    samples, _, _ = load_samples(ingested)
    train, val = split_by_stop(samples, 0.3, seed=1)
    assert train and val and not ({s.stop_id for s in train} & {s.stop_id for s in val})
    assert len(train) + len(val) == len(samples)
    assert [s.image_id for s in split_by_stop(samples, 0.3, seed=1)[1]] == [s.image_id for s in val]


def test_scaling_flipping_and_mapping_back(ingested):
    samples, _, _ = load_samples(ingested)
    s = next(x for x in samples if len(x.boxes))
    image, target = DetectionDataset([s], max_side=max(s.width, s.height) // 2)[0]
    scale = target["scale"]
    assert image.shape[1:] == (round(s.height * scale), round(s.width * scale))
    np.testing.assert_allclose(to_original(target["boxes"].numpy(), scale), s.boxes, rtol=1e-5)
    # With augmentation, some draw flips: a flipped box mirrors about the image's vertical centre line.
    aug = DetectionDataset([s] * 20, augment=True, seed=3)
    seen = set()
    for i in range(20):
        img, t = aug[i]
        b = t["boxes"].numpy()
        flipped = not np.allclose(b, s.boxes)
        if flipped:
            np.testing.assert_allclose(b[:, [2, 0]], s.width - s.boxes[:, [0, 2]], rtol=1e-5)
        seen.add(flipped)
        assert img.min() >= 0 and img.max() <= 1
    assert seen == {True, False}


def test_repeat_factors_follow_the_lvis_rule():
    from pathlib import Path

    import numpy as np

    from pipeline.detection.data import Sample, repeat_factors

    def sample(labels):
        return Sample("i", Path("i"), "s", 10, 10, np.zeros((len(labels), 4), np.float32), np.array(labels, np.int64))

    samples = [sample([1]), sample([1, 1]), sample([2, 1]), sample([3])]  # class shares 3/4, 1/4, 1/4
    np.testing.assert_allclose(repeat_factors(samples, 0.5), [1.0, 1.0, np.sqrt(2.0), np.sqrt(2.0)])
    np.testing.assert_allclose(repeat_factors(samples, 0.0), 1.0)
    np.testing.assert_allclose(repeat_factors(samples, 0.1), 1.0)  # no class rarer than the threshold
