"""A camera image to IPA and RPA descriptors through the bundle's ONNX detector (onnxruntime, no torch).

With a retrieval backbone other than the detector (`retrieval.backbone`), `describer.onnx` also holds that
backbone (outputs `backbone_map`, and `backbone_ipa` with a NetVLAD / GeM head) and `describer.json` its
record under `retrieval_backbone` (name, stride, dims, weights and their sha256, outputs): the camera image
is described by the backbone the database was extracted with, through the same `describe_graph_outputs`
as `extract`. `describer.json`'s `ipa_pooling` (`sum` or `gem`, with `gem_p`) says how the IPA pools the
map, as the database's extraction did (`retrieval.pooling`); a bundle exported before it was recorded has
neither key and pools by sum.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.retrieval.descriptors import POOLINGS, ImageDescriptors, describe_graph_outputs
from pipeline.runtime.bundle import BundleError

OUTPUTS = ("feature_map", "proposals", "proposal_scores", "boxes", "scores", "labels")


def image_array(image) -> np.ndarray:
    """(3, H, W) float32 in [0, 1] from a path, an (H, W, 3) uint8 RGB array or a (3, H, W) float array. A file
    that cannot be decoded faithfully is refused by `pipeline.io.images` with an InputError naming it."""
    if isinstance(image, (str, Path)):
        from pipeline.io.images import image_rgb

        image = image_rgb(image)
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[-1] == 3 and a.dtype == np.uint8:
        return np.ascontiguousarray(a.transpose(2, 0, 1), dtype=np.float32) / 255.0
    if a.ndim == 3 and a.shape[0] == 3:
        return np.ascontiguousarray(a, dtype=np.float32)
    raise ValueError(f"an image must be (H, W, 3) uint8 RGB or (3, H, W) float in [0, 1], got {a.shape} {a.dtype}")


def camera_image(image, image_hw: tuple[int, int], graph: str) -> np.ndarray:
    """`image_array(image)`, refused unless it has the size the bundle's `graph` was exported for."""
    x = image_array(image)
    if tuple(x.shape[1:]) != tuple(image_hw):
        raise BundleError(f"camera image of {x.shape[2]} x {x.shape[1]} px; this bundle's {graph} was exported "
                          f"for {image_hw[1]} x {image_hw[0]} (the site camera): resize the image or export a "
                          f"bundle for this camera")
    return x


def graph_outputs(meta: dict) -> list[str]:
    """The outputs of the describer graph `meta` (its describer.json) describes images with."""
    return [*OUTPUTS, *(meta.get("retrieval_backbone") or {}).get("outputs", [])]


def describe_with(session, image: np.ndarray, meta: dict) -> ImageDescriptors:
    """IPA and RPA of one (3, H, W) image through an onnxruntime session of the detector graph, `meta` being
    its describer.json (scale, stride, rpa_proposals, rpa_min_score, ipa_pooling, gem_p, retrieval_backbone).
    `extract` describes the database with this too."""
    out = session.run(graph_outputs(meta), {"image": image})
    return describe_graph_outputs(out, meta, rpa_proposals=meta["rpa_proposals"], rpa_min_score=meta["rpa_min_score"])


class OnnxDescriber:
    def __init__(self, onnx_path: Path, meta_path: Path, *, threads: int | None = None):
        import onnxruntime as ort

        self.meta = json.loads(Path(meta_path).read_text())
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
        self.image_hw = tuple(self.meta["image_hw"])
        self.backbone = self.meta.get("retrieval_backbone")  # None: the detector's own map
        pooling, p = self.meta.get("ipa_pooling", "sum"), self.meta.get("gem_p", 3.0)
        if pooling not in POOLINGS or not isinstance(p, (int, float)) or not 0 < p <= 20:
            raise BundleError(f"{meta_path}: ipa_pooling {pooling!r} (gem_p {p!r}) is not one this runtime pools "
                              f"with ({', '.join(POOLINGS)}; gem_p in (0, 20]): update siteloc, or export the "
                              f"bundle again with this version")
        lacking = sorted(set(graph_outputs(self.meta)) - {o.name for o in self.session.get_outputs()})
        if lacking:
            raise BundleError(f"{onnx_path}: lacks the outputs {lacking} that {Path(meta_path).name} names; the "
                              f"bundle's files do not belong together: export it again")

    def describe(self, image) -> ImageDescriptors:
        return describe_with(self.session, camera_image(image, self.image_hw, "detector"), self.meta)
