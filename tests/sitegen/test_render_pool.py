"""`RenderPool`'s processes die with their parent: `kill -9` of `synth --workers 2` leaves no renderer behind."""

from __future__ import annotations

import sys

import pytest

from pipeline.sitegen.render import egl_available
from tests.test_workers import kill_parent_and_check_workers

pytestmark = pytest.mark.skipif(not egl_available(), reason="no headless EGL context on this machine")

# The micro preset's pool with 2 workers, each busy (past its initializer: render context open) with a long task,
# so neither leaves because its task queue closed: only dying with the parent ends it.
POOL = """
import sys, time
from pathlib import Path
from pipeline.sitegen.render_pool import RenderPool
from tests.sitegen.micro import micro
from tests.test_workers import mark_and_sleep

pool = RenderPool(micro(), 3, False, True, Path(sys.argv[1]) / "site", workers=2)
futures = [pool._pool.submit(mark_and_sleep, str(Path(sys.argv[1]) / "busy")) for _ in range(2)]
time.sleep(300)
"""


@pytest.mark.slow
def test_render_workers_die_when_synth_is_killed(tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()

    def workers(_parent_pid: int) -> list[int]:
        found = [int(p.name) for p in busy.iterdir()]
        return found if len(found) == 2 else []

    kill_parent_and_check_workers([sys.executable, "-c", POOL, str(tmp_path)], workers, timeout=240)
