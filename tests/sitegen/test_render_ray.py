"""`synth --engine ray`: the micro site rendered by Ray actors is byte for byte the one the process pool
renders, also when a worker dies mid-run."""

from __future__ import annotations

import json
import os
import sys

import pytest

from pipeline.sitegen.render import egl_available
from pipeline.sitegen.render_pool import RenderActor
from pipeline.sitegen.synth import TIMING_FILE
from tests.sitegen.micro import digests, synth

pytestmark = pytest.mark.skipif(not egl_available()[0], reason="no headless EGL context on this machine")
ray = pytest.importorskip("ray")



class CrashOnce(RenderActor):
    """Kills its worker process on the first batch any actor renders (the marker beside the site's output)."""

    def __init__(self, *args):
        super().__init__(*args)
        self.marker = os.path.join(os.path.dirname(args[4]), "crashed-once")

    def render(self, batch):
        if not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(1)
        return super().render(batch)


def test_ray_renders_the_process_pools_site_even_when_a_worker_dies(local_ray, site, tmp_path, monkeypatch):
    import cloudpickle

    from pipeline.sitegen import render_pool

    on_ray = synth(tmp_path / "ray", workers=2, executor="ray")
    assert digests(on_ray) == digests(site)
    timing = json.loads((on_ray / TIMING_FILE).read_text())
    assert timing["render_engine"] == "ray" and timing["render_workers"] == 2

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    monkeypatch.setattr(render_pool, "RenderActor", CrashOnce)
    again = synth(tmp_path / "again", workers=2, executor="ray")
    assert (tmp_path / "crashed-once").exists()  # a worker did die
    assert digests(again) == digests(site)
