"""Seeding the filter over whole areas from seed 001's (room, area) prior, at run time.

A bundle exported with a prior (`siteloc export --prior`) carries:

    models/prior.onnx        camera image (3, H, W) in [0, 1] -> the three layers' l2-normalised vectors
    models/prior.json        encoder settings and ONNX parity figures
    prior/                   the `prior build` output: compressions, database, Gaussians (arrays, Parquet, JSON)

`AreaPriorSeeder` turns a camera image into class probabilities and those into particle weights per
area: the `max_areas` most probable classes keep their probability, and each class's free space is the
map's free cells nearer to its stops than to any other class's, within `area_radius_m`. With
`filter.seed_with: area_prior` the Localizer starts the filter that way instead of around the Top-4
retrieved poses. numpy, scipy, scikit-learn's BallTree and onnxruntime only.
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import numpy as np

from pipeline.runtime.bundle import BundleError
from pipeline.runtime.describer import camera_image

FILES = ("models/prior.onnx", "models/prior.json", "prior/prior.json")


def has_prior(root: Path) -> bool:
    present = [(Path(root) / f).is_file() for f in FILES]
    if any(present) and not all(present):
        missing = [f for f, p in zip(FILES, present, strict=True) if not p]
        raise BundleError(f"{root}: the area prior is incomplete ({', '.join(missing)} missing); export the bundle "
                          "again")
    return all(present)


class AreaPriorSeeder:
    def __init__(self, root: Path, lmap, *, area_radius_m: float, max_areas: int, threads: int | None = None):
        import onnxruntime as ort

        from pipeline.prior.model import AreaPrior

        root = Path(root)
        self.meta = json.loads((root / "models" / "prior.json").read_text())
        self.prior = AreaPrior.load(root / "prior")
        if list(self.prior.layers) != list(self.meta["encoder"]["layers"]):
            raise BundleError(f"{root}: the prior's layers {self.prior.layers} are not its encoder's "
                              f"{self.meta['encoder']['layers']}; export the bundle again")
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(root / "models" / "prior.onnx"), options,
                                            providers=["CPUExecutionProvider"])
        self.image_hw = tuple(self.meta["image_hw"])
        self.max_areas = max_areas
        self._lmap, self._area_radius_m = lmap, area_radius_m

    @cached_property
    def cells(self) -> np.ndarray:
        """(K,) class of each free cell of the map (-1: none), computed when first needed: a bundle that seeds
        from poses does not pay for it at load."""
        return self.prior.area_cells(self._lmap, self._area_radius_m)

    def layers(self, image) -> dict[str, np.ndarray]:
        """The image's raw (uncompressed) layer vectors, each (1, D)."""
        x = camera_image(image, self.image_hw, "area-prior encoder")
        return {n: v[None] for n, v in zip(self.prior.layers, self.session.run(None, {"image": x}), strict=True)}

    def probabilities(self, image) -> np.ndarray:
        """(C,) probability of each (room, area) class of the prior."""
        return self.prior.probabilities(self.layers(image))[0]

    def weights(self, probs: np.ndarray) -> np.ndarray:
        """The `max_areas` most probable classes' probabilities (others 0): particle shares per area."""
        from pipeline.prior.model import top_areas

        return top_areas(probs, self.max_areas)
