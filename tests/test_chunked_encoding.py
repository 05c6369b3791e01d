"""Resumable chunked encoding, here and on a local Ray: the same arrays as a direct computation, a run resumed
from its finished chunks, another run's partial folder refused, a killed worker's chunk computed again; and
`frame-features` / `prior features` with --engine ray writing the local engine's tables."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.chunked_encoding import (
    ChunkEncoder,
    EncoderSpec,
    chunk_path,
    close_partial,
    encode_in_chunks,
    open_partial,
)
from pipeline.errors import SitelocError
from tests.fixtures.log_capture import Warnings


class Bar:
    def __init__(self):
        self.n = 0

    def update(self, n):
        self.n += n


def byte_stats(offset: float = 0.0):
    """An Encode of a file's bytes: their sum and a 3-value profile (a stand-in for a network)."""

    def encode(paths):
        data = [np.frombuffer(Path(p).read_bytes(), np.uint8).astype(np.float64) for p in paths]
        return {"sum": np.array([d.sum() + offset for d in data]),
                "profile": np.stack([[d.min(), d.max(), d.mean()] for d in data]).astype(np.float32)}

    return encode


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(0)
    paths = []
    for i in range(23):
        p = tmp_path / "images" / f"{i:03d}.bin"
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(rng.integers(0, 256, 50 + i, dtype=np.uint8).tobytes())
        paths.append(p)
    return paths


def test_chunks_give_the_arrays_of_one_pass_and_resume_where_they_stopped(files, tmp_path):
    partial = tmp_path / "out.partial"
    open_partial(partial, {"stage": "t"}, files)
    calls = []

    def counting(paths):
        calls.append(len(paths))
        if len(calls) == 3:
            raise KeyboardInterrupt
        return byte_stats()(paths)

    with pytest.raises(KeyboardInterrupt):
        encode_in_chunks(files, partial, 5, counting, Bar())
    assert calls == [5, 5, 5] and chunk_path(partial, 1).is_file() and not chunk_path(partial, 2).is_file()
    open_partial(partial, {"stage": "t"}, files)  # the same run again: its chunks are kept
    calls.clear()
    bar = Bar()
    got = encode_in_chunks(files, partial, 5, lambda p: (calls.append(len(p)), byte_stats()(p))[1], bar)
    assert calls == [5, 5, 3] and bar.n == len(files)
    want = byte_stats()(files)
    np.testing.assert_array_equal(got["sum"], want["sum"])
    np.testing.assert_array_equal(got["profile"], want["profile"])
    close_partial(partial)
    assert not partial.exists()


def test_another_runs_partial_folder_is_refused(files, tmp_path):
    partial = tmp_path / "out.partial"
    open_partial(partial, {"stage": "t", "chunk": 5}, files)
    with pytest.raises(SitelocError, match="another|other images or settings"):
        open_partial(partial, {"stage": "t", "chunk": 6}, files)
    with pytest.raises(SitelocError, match="other images or settings"):
        open_partial(partial, {"stage": "t", "chunk": 5}, files[:-1])


def _damage(path: Path, how: str) -> None:
    if how == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "garbage":
        path.write_bytes(b"\x1b[2J not a zip file " * 100)
    elif how == "wrong rows":
        np.savez(path, sum=np.zeros(2), profile=np.zeros((2, 3), np.float32))
    elif how == "wrong layout":
        np.savez(path, sum=np.zeros(5), profile=np.zeros((5, 4), np.float32))
    elif how == "a folder":
        path.unlink()
        path.mkdir()
        (path / "x").write_text("x")


@pytest.mark.parametrize("how", ["truncated", "garbage", "wrong rows", "wrong layout", "a folder"])
def test_a_damaged_chunk_is_discarded_with_a_warning_and_computed_again(files, tmp_path, how):
    """A corrupted chunk in the resume folder made every rerun fail; now it is named, deleted and redone."""
    partial = tmp_path / "out.partial"
    open_partial(partial, {"stage": "t"}, files)
    encode_in_chunks(files, partial, 5, byte_stats(), Bar())
    _damage(chunk_path(partial, 2), how)
    open_partial(partial, {"stage": "t"}, files)
    calls = []
    with Warnings("pipeline.chunked_encoding") as warned:
        got = encode_in_chunks(files, partial, 5, lambda p: (calls.append(len(p)), byte_stats()(p))[1], Bar())
    assert calls == [5]  # only the damaged chunk
    assert f"{chunk_path(partial, 2)}: damaged resume chunk" in warned.text and "computed again" in warned.text
    assert "\x1b" not in warned.text
    want = byte_stats()(files)
    np.testing.assert_array_equal(got["sum"], want["sum"])
    np.testing.assert_array_equal(got["profile"], want["profile"])


@pytest.mark.parametrize("plan", [b"{not json", b'["a list"]', b"\xff\xfe garbage", None])
def test_an_unreadable_plan_starts_afresh_and_force_always_does(files, tmp_path, plan):
    partial = tmp_path / "out.partial"
    open_partial(partial, {"stage": "t"}, files)
    encode_in_chunks(files, partial, 5, byte_stats(), Bar())
    if plan is None:
        (partial / "plan.json").unlink()
    else:
        (partial / "plan.json").write_bytes(plan)
    with Warnings("pipeline.chunked_encoding") as warned:
        open_partial(partial, {"stage": "t"}, files)
    assert f"{partial}: resume folder discarded, no readable plan.json" in warned.text
    assert sorted(p.name for p in partial.iterdir()) == ["plan.json"]
    # --force: whatever is there (garbage chunks, another run's plan, a stray folder) is deleted first.
    encode_in_chunks(files, partial, 5, byte_stats(), Bar())
    for k in range(5):
        chunk_path(partial, k).write_bytes(b"garbage")
    (partial / "stray").mkdir()
    open_partial(partial, {"stage": "t", "chunk": 6}, files, force=True)
    assert sorted(p.name for p in partial.iterdir()) == ["plan.json"]
    close_partial(partial)
    partial.write_bytes(b"a file where the folder goes")
    open_partial(partial, {"stage": "t"}, files, force=True)
    assert partial.is_dir()


def test_a_chunk_file_never_holds_pickles(files, tmp_path):
    partial = tmp_path / "p"
    open_partial(partial, {}, files)
    encode_in_chunks(files, partial, 50, byte_stats(), Bar())
    with np.load(chunk_path(partial, 0), allow_pickle=False) as z:
        assert sorted(z.files) == ["profile", "sum"]


class CrashOnce(ChunkEncoder):
    """Kills its worker process on the first chunk any actor runs."""

    def __call__(self, batch):
        marker = self.partial.parent / "crashed-once"
        if not marker.exists():
            marker.write_text("x")
            os._exit(1)
        return super().__call__(batch)


def test_ray_actors_give_the_same_arrays_and_survive_a_killed_worker(local_ray, files, tmp_path, monkeypatch):
    import cloudpickle

    from pipeline import chunked_encoding

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # byte_stats and CrashOnce, for Ray's workers
    monkeypatch.setattr(chunked_encoding, "ChunkEncoder", CrashOnce)
    partial = tmp_path / "out.partial"
    open_partial(partial, {}, files)
    bar = Bar()
    got = encode_in_chunks(files, partial, 4, None, bar, executor="ray", spec=lambda: EncoderSpec(byte_stats))
    assert (tmp_path / "crashed-once").exists() and bar.n == len(files)
    want = byte_stats()(files)
    np.testing.assert_array_equal(got["sum"], want["sum"])
    np.testing.assert_array_equal(got["profile"], want["profile"])


def test_frame_features_on_ray_write_the_local_table(local_ray, micro_frames, tmp_path):
    from pipeline.io import tables
    from pipeline.sequence.frames import run_frame_features

    cfg, ing, local = micro_frames
    cfg = cfg.model_copy(update={"sequence": cfg.sequence.model_copy(update={"chunk": 8})})  # several chunks
    out = run_frame_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "ray"}, progress=False,
                             executor="ray")
    a, b = tables.read_table(local / "frames.parquet", "frames"), tables.read_table(out / "frames.parquet", "frames")
    assert a.num_rows > 8
    assert a.drop_columns(["descriptor"]).equals(b.drop_columns(["descriptor"]))
    np.testing.assert_array_equal(tables.descriptor_matrix(a), tables.descriptor_matrix(b))  # bit for bit
    assert json.loads((out / "report.json").read_text())["computed_frames"] == a.num_rows
    assert not (tmp_path / "ray.partial").exists()


def test_prior_features_on_ray_write_the_local_vectors(local_ray, micro_site, tmp_path):
    from pipeline.config import load_config
    from pipeline.prior.features import read_layers, run_prior_features

    _, ing, _ = micro_site
    cfg = load_config("ci", ["prior.weights=null", "prior.input_size=64", "prior.device=cpu", "prior.chunk=16",
                             "prior.batch=8"])
    local = run_prior_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "local"}, progress=False)
    on_ray = run_prior_features(cfg, inputs={"data": ing}, outputs={"out": tmp_path / "ray"}, progress=False,
                                executor="ray")
    (ma, ra, _), (mb, rb, _) = read_layers(local), read_layers(on_ray)
    assert ma == mb and len(ma["image_id"]) > 16
    for layer in ra:
        np.testing.assert_array_equal(ra[layer], rb[layer])


def test_torch_on_ray_is_refused_naming_the_setting():
    from pipeline.chunked_encoding import refuse_torch_on_ray
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="set prior.engine to auto"):
        refuse_torch_on_ray("torch", "ray", "prior.engine")
    refuse_torch_on_ray("torch", "local", "prior.engine")
    refuse_torch_on_ray("onnx", "ray", "prior.engine")
