"""`extract --engine ray` on a local Ray: the same tables as the local engine, a worker killed mid-run, a
resumed run, and the errors for a missing extra or an address where no cluster answers."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import SitelocError
from pipeline.io import tables
from pipeline.retrieval.extract_ray import ChunkDescriber

ray = pytest.importorskip("ray")



def _same_tables(a: Path, b: Path) -> None:
    for kind in ("ipa", "rpa"):
        ta, tb = tables.read_table(a / f"{kind}.parquet", kind), tables.read_table(b / f"{kind}.parquet", kind)
        assert ta.drop_columns(["descriptor"]).equals(tb.drop_columns(["descriptor"]))
        np.testing.assert_array_equal(tables.descriptor_matrix(ta), tables.descriptor_matrix(tb))  # bit for bit
    assert tables.read_table(a / "catalog.parquet", "catalog").equals(tables.read_table(b / "catalog.parquet",
                                                                                         "catalog"))


class CrashOnce(ChunkDescriber):
    """Dies (the whole worker process) on its first chunk, the first time any actor runs one."""

    def __call__(self, batch):
        marker = self.partial.parent / "crashed-once"
        if not marker.exists():
            marker.write_text("x")
            os._exit(1)
        return super().__call__(batch)


def test_ray_writes_the_local_engines_tables(local_ray, micro_site, micro_extraction, tmp_path):
    from pipeline.retrieval.extract import run_extract

    cfg, ing, model = micro_site
    out = run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path / "ray"}, progress=False,
                      executor="ray")
    _same_tables(out, micro_extraction)
    report = json.loads((out / "report.json").read_text())
    assert report["computed_images"] == report["images"]
    assert not (tmp_path / "ray.partial").exists()


def test_a_worker_killed_mid_run_is_retried_and_the_tables_are_the_same(local_ray, micro_site, micro_extraction,
                                                                        tmp_path, monkeypatch):
    import cloudpickle

    from pipeline.retrieval import extract_ray
    from pipeline.retrieval.extract import run_extract

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the crashing actor, for Ray's workers
    real = extract_ray.extract_on_ray
    monkeypatch.setattr(extract_ray, "extract_on_ray", lambda *a, **k: real(*a, **k, actor=CrashOnce))
    cfg, ing, model = micro_site
    out = run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": tmp_path / "ray"}, progress=False,
                      executor="ray")
    assert (tmp_path / "crashed-once").exists()  # a worker did die
    _same_tables(out, micro_extraction)


def test_an_interrupted_run_resumes_from_its_finished_chunks(local_ray, micro_site, micro_extraction, tmp_path):
    from pipeline.retrieval.extract import run_extract, site_images

    cfg, ing, model = micro_site
    out = tmp_path / "ray"
    # An interrupted local run left the first chunk: the Ray run describes only the rest.
    from pipeline.retrieval import extract as extract_mod

    calls = []
    real_write = extract_mod.write_chunk

    def stop_after_first(partial, k, ids, described):
        real_write(partial, k, ids, described)
        calls.append(k)
        raise KeyboardInterrupt

    extract_mod.write_chunk = stop_after_first
    try:
        with pytest.raises(KeyboardInterrupt):
            run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": out}, progress=False)
    finally:
        extract_mod.write_chunk = real_write
    assert calls == [0]
    result = run_extract(cfg, inputs={"model": model, "data": ing}, outputs={"out": out}, progress=False,
                         executor="ray")
    images = site_images(ing, include_runs=cfg.retrieval.include_runs)
    report = json.loads((result / "report.json").read_text())
    assert report["computed_images"] == len(images) - cfg.retrieval.chunk
    _same_tables(result, micro_extraction)


def test_an_address_where_no_cluster_answers_is_refused_with_the_fix():
    from pipeline.ray_engine import _reachable

    with pytest.raises(SitelocError, match="ray start --head"):
        _reachable("127.0.0.1:1")
    with pytest.raises(SitelocError, match="not host:port"):
        _reachable("nonsense")


def test_without_ray_installed_the_error_names_the_extra(monkeypatch):
    from pipeline.ray_engine import connect

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(SitelocError, match=r"siteloc\[ray\]"):
        connect(None)
