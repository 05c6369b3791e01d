"""Descriptors of unchanged images taken from an earlier extraction (`siteloc extract --reuse`).

After `siteloc update`, most images of a site are the same files as before. An image's IPA and RPA rows
depend only on its content and on the describer: the detector's weights, the retrieval backbone, the
engine, the IPA pooling and the RPA settings. So rows are keyed by the image's sha256 and reused when the
earlier extraction's describer key equals this one; every other image is described afresh (an earlier
extraction pooled otherwise is named in a warning and in report.json's `reuse.describer_differs`). The
result is the extraction a full run would write, row for row.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.io import tables
from pipeline.io.image_reuse import HASHES_FILE, EarlierImages
from pipeline.retrieval.descriptors import ImageDescriptors, pooling_label, pooling_sets, recorded_pooling

log = logging.getLogger(__name__)


def describer_key(weights_sha256: str, settings: dict) -> str:
    """sha256 of what an image's descriptors depend on besides the image (`pooling`: absent for sum)."""
    keep = {k: settings[k] for k in ("rpa_proposals", "rpa_min_score", "engine", "backbone", "pooling")
            if k in settings}
    return hashlib.sha256((weights_sha256 + json.dumps(keep, sort_keys=True)).encode()).hexdigest()


class ReusedDescriptors:
    """The rows of an earlier extraction, by image sha256; empty when its describer differs (`matches`).

    `pooling`: this run's (retrieval.pooling, retrieval.gem_p); when the earlier extraction recorded
    another, `differs` says so and a warning names both."""

    def __init__(self, directory: Path, describer: str, *, pooling: tuple[str, float] | None = None):
        directory = Path(directory)
        earlier = EarlierImages(directory, describer, report_field="describer_sha256", stage="extract")
        self.directory, self.matches, self.differs = directory, earlier.matches, None
        self._rows: dict[str, ImageDescriptors] = {}
        if not self.matches:
            if pooling is not None:
                was = recorded_pooling(json.loads((directory / "report.json").read_text()))
                now = (pooling[0], float(pooling[1]) if pooling[0] == "gem" else None)
                if was != now:
                    self.differs = f"retrieval.pooling: {pooling_label(*was)} there, {pooling_label(*now)} here"
                    log.warning("warning: %s: extracted with retrieval.pooling %s, this run pools %s: none of its "
                                "rows are reused, every image is described afresh (extract with %s to reuse "
                                "them)", directory, pooling_label(*was), pooling_label(*now), pooling_sets(*was))
            return
        sha = tables.read_table(directory / HASHES_FILE, "image_hashes").to_pydict()
        by_id = dict(zip(sha["image_id"], sha["sha256"], strict=True))
        ipa = tables.read_table(directory / "ipa.parquet", "ipa")
        ipa_desc = tables.descriptor_matrix(ipa)
        rpa = tables.read_table(directory / "rpa.parquet", "rpa")
        rpa_desc = tables.descriptor_matrix(rpa)
        r = rpa.drop(["descriptor"]).to_pydict()
        regions: dict[str, list[int]] = {}
        for k, image_id in enumerate(r["image_id"]):
            regions.setdefault(image_id, []).append(k)
        for row, image_id in enumerate(ipa.column("image_id").to_pylist()):
            if image_id not in by_id:
                continue
            ks = regions.get(image_id, [])
            self._rows[by_id[image_id]] = ImageDescriptors(
                ipa=ipa_desc[row],
                boxes=np.array([[r["x1"][k], r["y1"][k], r["x2"][k], r["y2"][k]] for k in ks],
                               dtype=np.float32).reshape(-1, 4),
                meta=[(r["source"][k], r["score"][k], r["class_id"][k]) for k in ks],
                rpa=rpa_desc[ks] if ks else np.zeros((0, ipa_desc.shape[1]), np.float32))

    def get(self, sha256: str) -> ImageDescriptors | None:
        return self._rows.get(sha256)

    def __len__(self) -> int:
        return len(self._rows)
