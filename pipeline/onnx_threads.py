"""Offline CPU inference through onnxruntime: one exported graph per image size, run in several threads.

`extract` and `frame-features` describe thousands of images with networks the bundle later carries as ONNX.
On 2 CPU cores onnxruntime runs them 2.0-3.3x faster than eager torch with one session using both cores
(EfficientNet-Lite0's depthwise convolutions are where torch loses), and 2.7-3.9x with one single-threaded
session per core, one image each (small convolutions do not split well); `benchmarks/offline_inference.py`.
So each stage exports its network at the size of the images it meets, checks the graph against torch on the
first images of that size (the stage fails beyond the check's tolerance, nothing is written), and then
describes every image through onnxruntime, which releases the GIL while it runs.

`engine: auto` picks onnxruntime when the stage runs on the CPU and torch on a GPU (onnxruntime's CUDA build
is not a dependency).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

MAX_WORKERS = 8  # beyond this, more sessions only cost memory: each holds its own copy of the weights


def resolve_engine(engine: str, device_type: str) -> str:
    """"torch" or "onnx" for a stage's `engine` setting (auto / torch / onnx) on a torch device type."""
    if engine == "auto":
        return "onnx" if device_type == "cpu" else "torch"
    if engine not in ("torch", "onnx"):
        raise ValueError(f"engine must be auto, torch or onnx, got '{engine}'")
    return engine


def thread_layout(cores: int | None = None) -> tuple[int, int]:
    """(worker threads, onnxruntime intra-op threads per worker) filling `cores` (default: the usable ones)."""
    if cores is None:
        from pipeline.machine import usable_core_count

        cores = usable_core_count()
    workers = max(1, min(int(cores), MAX_WORKERS))
    return workers, max(1, int(cores) // workers)


class SizedGraphPool:
    """Runs `run(session, image)` over images, with one ONNX graph per image size.

    `build(image_hw, samples, path) -> info` exports the graph for images of `image_hw` to `path` and checks it
    on `samples` (the first images of that size, (3, H, W) float32 arrays); it raises when the check fails.
    `run(session, image, info)` gives one image's result. `layout`: (worker threads, intra-op threads each),
    by default `thread_layout()`. Graphs go to `workdir/<name>-<H>x<W>.onnx`; `info` per
    size is kept in `.graphs` (keyed "<W>x<H>") for the stage's report.
    """

    def __init__(self, name: str, workdir: Path, build: Callable[[tuple[int, int], list, Path], dict],
                 run: Callable[[Any, np.ndarray, dict], Any], *, samples: int = 4,
                 layout: tuple[int, int] | None = None):
        self.name, self.workdir, self._build, self._run, self.samples = name, Path(workdir), build, run, samples
        self.workers, self.threads = layout or thread_layout()
        self.graphs: dict[str, dict] = {}
        self._paths: dict[tuple[int, int], Path] = {}
        self._info: dict[tuple[int, int], dict] = {}
        self._local = threading.local()
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix=f"onnx-{name}")

    def __call__(self, paths: Sequence[Path]) -> list:
        """`run` of each image file (decoded in the worker threads), in order."""
        from pipeline.runtime.describer import image_array

        images = list(self._pool.map(image_array, paths))
        by_size: dict[tuple[int, int], list[np.ndarray]] = {}
        for im in images:
            by_size.setdefault(tuple(int(v) for v in im.shape[1:]), []).append(im)
        for hw, same in by_size.items():
            if hw not in self._paths:
                path = self.workdir / f"{self.name}-{hw[0]}x{hw[1]}.onnx"
                self._info[hw] = self.graphs[f"{hw[1]}x{hw[0]}"] = self._build(hw, same[: self.samples], path)
                self._paths[hw] = path
        return list(self._pool.map(self._one, images))

    def _one(self, image: np.ndarray):
        hw = tuple(int(v) for v in image.shape[1:])
        sessions = getattr(self._local, "sessions", None)
        if sessions is None:
            sessions = self._local.sessions = {}
        if hw not in sessions:
            import onnxruntime as ort

            options = ort.SessionOptions()
            options.intra_op_num_threads = self.threads
            options.inter_op_num_threads = 1
            sessions[hw] = ort.InferenceSession(str(self._paths[hw]), options, providers=["CPUExecutionProvider"])
        return self._run(sessions[hw], image, self._info[hw])

    def graph_files(self) -> dict[str, tuple[Path, dict]]:
        """The graphs exported so far: "<W>x<H>" -> (file, info)."""
        return {f"{hw[1]}x{hw[0]}": (path, self._info[hw]) for hw, path in self._paths.items()}

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def __enter__(self) -> SizedGraphPool:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
