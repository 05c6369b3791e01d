"""Image-sequence re-localization at run time (seed 000 section 3.3): the last frames, not the last frame.

A bundle exported with a sequence model (`siteloc export --sequence`) carries:

    models/frames.onnx       camera image (3, H, W) in [0, 1] -> 1000 ImageNet logits (EfficientNet-Lite0)
    models/sequence.onnx     frame logits (B, T, 1000) -> pooled LSTM descriptor (B, hidden), dynamic T
    models/sequence.json     length, parity figures, encoder settings
    sequence/database.parquet, sequence/whitening.npz   the mapping runs' whitened sequence descriptors + poses

`SequenceRelocaliser` keeps a ring buffer of the most recent frames, encoded only when a sequence query
needs them: the encoder costs about 16 ms a frame on 2 cores, and sequences are queried only while the
filter re-localizes, so a tracking robot pays nothing for it. The Localizer clears the buffer when
the filter declares itself lost, keeping only the frames since the kidnap rule started counting (those
were seen where the robot is now), and once `length` frames are in it, the sequence's Top-K database
windows give candidate poses (the pose of each window's last frame) to inject around. numpy and
onnxruntime only.
"""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path

import numpy as np

from pipeline.runtime.bundle import BundleError
from pipeline.runtime.describer import camera_image

FILES = ("models/frames.onnx", "models/sequence.onnx", "models/sequence.json", "sequence/database.parquet",
         "sequence/whitening.npz")


def has_sequence(root: Path) -> bool:
    """Whether the bundle carries the sequence models (all of them, or it is refused as incomplete)."""
    present = [(Path(root) / f).is_file() for f in FILES]
    if any(present) and not all(present):
        missing = [f for f, p in zip(FILES, present, strict=True) if not p]
        raise BundleError(f"{root}: the sequence re-localization is incomplete ({', '.join(missing)} missing); "
                          f"export the bundle again")
    return all(present)


class SequenceRelocaliser:
    def __init__(self, root: Path, *, threads: int | None = None):
        import onnxruntime as ort

        from pipeline.io import tables
        from pipeline.retrieval.whitening import PCAWhitening

        root = Path(root)
        self.meta = json.loads((root / "models" / "sequence.json").read_text())
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
        self.frames = ort.InferenceSession(str(root / "models" / "frames.onnx"), options,
                                           providers=["CPUExecutionProvider"])
        self.lstm = ort.InferenceSession(str(root / "models" / "sequence.onnx"), options,
                                         providers=["CPUExecutionProvider"])
        self.whitening = PCAWhitening.load(root / "sequence" / "whitening.npz")
        t = tables.read_table(root / "sequence" / "database.parquet", "sequences")
        self.db = tables.descriptor_matrix(t).astype(np.float32)
        self.db_poses = np.column_stack([t.column(c).to_numpy() for c in ("x", "y", "theta")])
        self.length = int(self.meta["length"])
        self.image_hw = tuple(self.meta["frames"]["image_hw"])
        self.buffer: deque[list] = deque(maxlen=self.length)  # [image, its logits once encoded]

    def encode(self, image) -> np.ndarray:
        """The frame's 1000 logits (the LSTM's input)."""
        return self.frames.run(None, {"image": camera_image(image, self.image_hw, "frame encoder")})[0]

    def push(self, image) -> None:
        """Keep a frame (a path, or a copy of the array: a camera driver may reuse its buffer)."""
        self.buffer.append([image if isinstance(image, (str, Path)) else np.array(image, copy=True), None])

    def logits(self) -> np.ndarray:
        """(T, 1000) logits of the buffered frames, oldest first; each frame is encoded once."""
        for entry in self.buffer:
            if entry[1] is None:
                entry[0], entry[1] = None, self.encode(entry[0])
        return np.stack([entry[1] for entry in self.buffer])

    def keep_last(self, n: int) -> None:
        """Drop all but the `n` most recent frames (n = 0 empties the buffer)."""
        while len(self.buffer) > max(n, 0):
            self.buffer.popleft()

    @property
    def ready(self) -> bool:
        return len(self.buffer) >= self.length

    def describe(self, frames: np.ndarray) -> np.ndarray:
        """(T, 1000) frame logits -> whitened sequence descriptor (dims,)."""
        pooled = self.lstm.run(None, {"frames": np.asarray(frames, np.float32)[None]})[0]
        return self.whitening.transform(pooled)[0]

    def ranked(self, n: int) -> np.ndarray:
        """(n, 3) x, y, theta of the buffer's Top-n database windows (the pose of each one's last frame), by
        inner product of whitened descriptors, best first; fewer when the database is smaller."""
        if not self.buffer:
            raise BundleError("no frames in the sequence buffer yet")
        q = self.describe(self.logits())
        top = np.argsort(-(self.db @ q), kind="stable")[: min(n, len(self.db))]
        return self.db_poses[top]

    def candidates(self, weights=(4.0, 3.0, 2.0, 1.0)) -> np.ndarray:
        """(K, 4) x, y, theta, weight of the buffer's Top-K database windows (K = len(weights)), one candidate
        per database window; weights normalised."""
        from pipeline.retrieval.search import weighted_candidates

        return weighted_candidates(self.ranked(len(weights)), weights)
