"""Image encodings computed in resumable chunks, in this process or on Ray actors (`--engine ray`).

`frame-features` and `prior features` turn every image of a site into arrays. Both hand `encode_in_chunks`
the image files still to encode, a `.partial` folder beside their output and a chunk size: each chunk's
arrays go to `partial/chunk-<k>.npz`, written under a temporary name and renamed, so a chunk is done exactly
when its file exists, an interrupted run resumes from the finished chunks, and a chunk lost with a Ray
worker is simply computed again. `plan.json` holds a fingerprint of the inputs and settings: the partial
folder of another run is refused rather than mixed in.

Resuming trusts nothing on disk (`start_partial`, `checked_chunk`, shared with `extract`'s Parquet chunks):
each finished chunk is read in full and checked against what it should hold (its row count, its arrays'
names and shapes); a damaged one is deleted with a warning naming it and computed again, and a folder without
a readable plan.json is started afresh. `--force` always starts clean: the partial folder is deleted first.

Locally the stage's own encoder (its thread pool of ONNX sessions, or torch) runs each chunk. On Ray each
actor builds the encoder from an `EncoderSpec` (a module-level factory and its keyword arguments, so it
pickles by reference) once, then encodes chunk after chunk. The arrays are the same either way: the ONNX
stages export and check their graphs here first (`export_graphs`) and the actors open those files.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from pipeline.errors import SitelocError, excerpt

Encode = Callable[[list[Path]], dict[str, np.ndarray]]  # image files -> {name: (len(files), ...) array}
T = TypeVar("T")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EncoderSpec:
    """How a Ray actor builds the encoder: `factory(**kwargs)` returns an `Encode`."""

    factory: Callable[..., Encode]
    kwargs: dict = field(default_factory=dict)

    def build(self) -> Encode:
        return self.factory(**self.kwargs)


def open_partial(partial: Path, settings: dict, paths: Sequence[Path], *, force: bool = False) -> None:
    """Create `partial` for a run of these settings and images, or keep the one an interrupted identical run
    left; refuse the partial folder of another run. `force` deletes whatever is there first."""
    h = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    for p in paths:
        h.update(str(p).encode() + b"\0")
    start_partial(partial, h.hexdigest(), len(paths), force=force)


def start_partial(partial: Path, fingerprint: str, images: int, *, force: bool = False,
                  inputs: Iterable[Path | str | None] = (), other: str = "an interrupted run with other images or "
                  "settings") -> None:
    """Make `partial` the resume folder of the run `fingerprint` names and write its plan.json.

    Kept when an interrupted identical run left it; deleted first with `force`, or (with a warning) when it is
    not a folder or has no readable plan.json; refused (SitelocError, `other` saying whose it is) when its plan
    is another run's. `inputs`: a partial folder that overlaps one of them is refused, never deleted.
    """
    from pipeline.io.atomic import refuse_overlap, write_text_atomic

    partial = Path(partial)
    plan = partial / "plan.json"
    if partial.exists() or partial.is_symlink():
        refuse_overlap(partial, inputs)
        damaged = None
        if not force:
            try:
                found = json.loads(plan.read_text(encoding="utf-8"))["fingerprint"]
            except (OSError, ValueError, KeyError, TypeError) as exc:
                damaged = f"no readable plan.json ({excerpt(exc, 80)})"
            else:
                if found != fingerprint:
                    raise SitelocError(f"{partial}: {other} is there; delete it, rerun with --force, or rerun that "
                                       f"command to start afresh")
        if force or damaged:
            if damaged and not (partial.is_dir() and not any(partial.iterdir())):
                log.warning("warning: %s: resume folder discarded, %s; starting afresh", partial, damaged)
            remove_entry(partial)
    partial.mkdir(parents=True, exist_ok=True)
    write_text_atomic(plan, json.dumps({"fingerprint": fingerprint, "images": images}) + "\n")


def checked_chunk(files: Sequence[Path], check: Callable[[], T]) -> T | None:
    """What `check()` returns (it reads a finished chunk's `files` in full and raises if they do not hold what
    they should), or None after deleting the files with a warning: a damaged chunk is computed again rather
    than failing every rerun."""
    try:
        return check()
    except Exception as exc:  # any failure to read or match means the chunk cannot be trusted
        log.warning("warning: %s: damaged resume chunk (%s); it is computed again", files[0], excerpt(exc, 120))
        for f in files:
            remove_entry(Path(f))
        return None


def remove_entry(path: Path) -> None:
    """Delete a file, link or folder (whatever a damaged resume folder holds there)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def chunk_path(partial: Path, k: int) -> Path:
    return Path(partial) / f"chunk-{k:05d}.npz"


def write_chunk(partial: Path, k: int, arrays: dict[str, np.ndarray]) -> None:
    from pipeline.io.atomic import atomic_file

    with atomic_file(chunk_path(partial, k)) as f:
        np.savez(f, **arrays)


def read_chunk(partial: Path, k: int) -> dict[str, np.ndarray]:
    with np.load(chunk_path(partial, k), allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


def _layout(arrays: dict[str, np.ndarray]) -> dict[str, tuple]:
    """Each array's row shape and dtype: what every chunk of one run shares."""
    return {name: (a.shape[1:], a.dtype.str) for name, a in sorted(arrays.items())}


def _checked_npz(partial: Path, k: int, n: int, layout: dict[str, tuple] | None) -> dict[str, np.ndarray]:
    """Chunk k read in full; ValueError unless every array has `n` rows (and, given one, `layout`)."""
    arrays = read_chunk(partial, k)
    rows = {name: (len(a) if a.ndim else 0) for name, a in arrays.items()}
    if not arrays or set(rows.values()) != {n}:
        raise ValueError(f"rows per array {rows}, the chunk has {n} images")
    if layout is not None and _layout(arrays) != layout:
        raise ValueError(f"arrays {_layout(arrays)}, the other chunks hold {layout}")
    return arrays


def _finished_chunks(partial: Path, chunks: list[list[Path]]) -> dict[int, dict[str, np.ndarray]]:
    """The chunks already in `partial`, read and checked (rows = the chunk's images; the same arrays, row shapes
    and dtypes as the other chunks); damaged ones are deleted (`checked_chunk`)."""
    from functools import partial as bind

    done: dict[int, dict[str, np.ndarray]] = {}
    layout: dict[str, tuple] | None = None
    for k, c in enumerate(chunks):
        path = chunk_path(partial, k)
        if path.exists() or path.is_symlink():
            arrays = checked_chunk([path], bind(_checked_npz, partial, k, len(c), layout))
            if arrays is not None:
                done[k] = arrays
                layout = layout or _layout(arrays)
    return done


def encode_in_chunks(paths: Sequence[Path], partial: Path, chunk: int, encode: Encode | None, bar, *,
                     executor: str = "local", spec: Callable[[], EncoderSpec] | None = None,
                     ray_address: str | None = None) -> dict[str, np.ndarray]:
    """{name: array over all `paths`, in order}, chunk by chunk through `encode` here (executor "local") or on
    Ray actors built from `spec()` (called only when chunks remain: it may export graphs). `partial` must be
    opened (`open_partial`); `bar` advances by images."""
    paths = [Path(p) for p in paths]
    chunks = [paths[i:i + chunk] for i in range(0, len(paths), chunk)]
    done = _finished_chunks(partial, chunks)
    pending = [k for k in range(len(chunks)) if k not in done]
    todo = set(pending)
    bar.update(sum(len(c) for k, c in enumerate(chunks) if k not in todo))
    if executor == "local":
        for k in pending:
            write_chunk(partial, k, encode(chunks[k]))
            bar.update(len(chunks[k]))
    elif executor == "ray":
        if pending:
            from pipeline.ray_engine import run_on_ray

            built = spec()
            run_on_ray(ray_address, [{"chunk": k, "paths": [str(p) for p in chunks[k]]} for k in pending],
                       ChunkEncoder, {"partial": str(partial), "spec": built}, on_done=lambda _k, n: bar.update(n))
    else:
        raise ValueError(f"executor must be local or ray, got '{executor}'")
    parts = [done[k] if k in done else read_chunk(partial, k) for k in range(len(chunks))]
    if not parts:
        return {}
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def close_partial(partial: Path) -> None:
    """Remove the partial folder once the stage's output is in place."""
    remove_entry(Path(partial))


class ChunkEncoder:
    """A Ray actor: builds the encoder once, then encodes one chunk per call and writes its file."""

    def __init__(self, partial: str, spec: EncoderSpec):
        self.partial, self.encode = Path(partial), spec.build()

    def __call__(self, batch: dict) -> dict:
        k = int(batch["chunk"][0])
        paths = [Path(str(p)) for p in batch["paths"][0]]
        arrays = self.encode(paths)
        write_chunk(self.partial, k, arrays)
        return {"chunk": np.array([k]), "items": np.array([len(paths)])}


def export_graphs(paths: Sequence[Path], pool) -> dict[str, tuple[str, dict]]:
    """Export and check (through the stage's `SizedGraphPool`) a graph for every image size among `paths`;
    "<W>x<H>" -> (graph file, info)."""
    from pipeline.io.images import image_size

    first: dict[tuple[int, int], Path] = {}
    for p in paths:
        w, h = image_size(p)
        first.setdefault((h, w), Path(p))
    pool(list(first.values()))
    return {key: (str(path), info) for key, (path, info) in pool.graph_files().items()}


class SizedSessions:
    """One single-threaded onnxruntime session per image size (one actor per core), opened on first use from
    the exported graphs ("<W>x<H>" -> (file, info)); an image of a size without a graph is refused."""

    def __init__(self, graphs: dict[str, tuple[str, dict]]):
        self.graphs, self.sessions = graphs, {}

    def __call__(self, path: Path) -> tuple[object, np.ndarray, dict]:
        """(session, image, the graph's info) for the image file at `path`."""
        from pipeline.runtime.describer import image_array

        image = image_array(path)
        key = f"{image.shape[2]}x{image.shape[1]}"
        if key not in self.graphs:
            raise SitelocError(f"{path}: an image of {key} pixels, for which no graph was exported "
                               f"(sizes: {sorted(self.graphs)})")
        if key not in self.sessions:
            import onnxruntime as ort

            options = ort.SessionOptions()
            options.intra_op_num_threads = 1
            options.inter_op_num_threads = 1
            self.sessions[key] = ort.InferenceSession(self.graphs[key][0], options,
                                                      providers=["CPUExecutionProvider"])
        return self.sessions[key], image, self.graphs[key][1]


def graph_encoder(graphs: dict[str, tuple[str, dict]], outputs: list[str]) -> Encode:
    """An `Encode` running each image through its size's graph and naming the graph's outputs `outputs`."""
    sessions = SizedSessions(graphs)

    def encode(paths: list[Path]) -> dict[str, np.ndarray]:
        rows: dict[str, list] = {name: [] for name in outputs}
        for p in paths:
            session, image, _ = sessions(p)
            for name, value in zip(outputs, session.run(None, {"image": image}), strict=True):
                rows[name].append(value)
        return {name: np.stack(v) for name, v in rows.items()}

    return encode


def encode_with_graphs(name: str, build: Callable[[tuple[int, int], list, Path], dict], outputs: list[str],
                       paths: Sequence[Path], partial: Path, chunk: int, bar, *, samples: int, executor: str = "local",
                       ray_address: str | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """`encode_in_chunks` through ONNX graphs: `build(image_hw, sample_images, path)` exports and checks one per
    image size (`pipeline.onnx_threads.SizedGraphPool`), whose outputs are `outputs`; locally the pool's threads
    run them, on Ray each actor opens the same files (`graph_encoder`). Returns the arrays and, when graphs were
    exported, the pool's layout and their parity figures (the graphs themselves live in a temporary directory:
    the bundle exports its own)."""
    import tempfile

    from pipeline.onnx_threads import SizedGraphPool

    def run(session, image: np.ndarray, _info: dict) -> list[np.ndarray]:
        return session.run(None, {"image": image})

    with tempfile.TemporaryDirectory(prefix=f"siteloc-{name}-") as workdir, \
            SizedGraphPool(name, Path(workdir), build, run, samples=samples) as pool:
        def encode(files: list[Path]) -> dict[str, np.ndarray]:
            out = pool(files)
            return {key: np.stack([o[i] for o in out]) for i, key in enumerate(outputs)}

        def spec() -> EncoderSpec:
            return EncoderSpec(graph_encoder, {"graphs": export_graphs(paths, pool), "outputs": list(outputs)})

        arrays = encode_in_chunks(paths, partial, chunk, encode, bar, executor=executor, spec=spec,
                                  ray_address=ray_address)
        graphs = {"workers": pool.workers, "threads_per_worker": pool.threads, "graphs": pool.graphs}
    return arrays, graphs if graphs["graphs"] else {}


def refuse_torch_on_ray(engine: str, executor: str, setting: str) -> None:
    """`--engine ray` runs exported graphs: a ConfigError naming `setting` when the stage's engine is torch."""
    if engine == "torch" and executor == "ray":
        from pipeline.errors import ConfigError

        raise ConfigError(f"--engine ray runs the exported ONNX graph: set {setting} to auto (on a CPU) or onnx")
