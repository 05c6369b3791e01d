"""Pool workers die with their parent: `kill -9` of the parent leaves no worker behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

ROOT = Path(__file__).resolve().parents[1]


def mark_and_sleep(folder: str) -> None:
    """A task: say which worker runs it, then outlive the test."""
    Path(folder, str(os.getpid())).touch()
    time.sleep(120)


def watchdog_only(parent_pid: int) -> None:
    """An initializer taking the non-Linux path of `die_with_parent` (the polling thread)."""
    import pipeline.workers as workers

    workers._pdeathsig = lambda _sig: False
    workers.POLL_S = 0.1
    workers.die_with_parent(parent_pid)


POOL = """
import multiprocessing, os, sys, time
from concurrent.futures import ProcessPoolExecutor
from pipeline.workers import die_with_parent
from tests.test_workers import mark_and_sleep, watchdog_only

init = watchdog_only if sys.argv[2] == "watchdog" else die_with_parent
pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"), initializer=init,
                           initargs=(os.getpid(),))
futures = [pool.submit(mark_and_sleep, sys.argv[1]) for _ in range(2)]
time.sleep(300)
"""


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE  # re-parented, not yet reaped: dead
    except psutil.NoSuchProcess:
        return True


def _wait_for(predicate, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def kill_parent_and_check_workers(command: list[str], workers_alive, timeout: float = 60.0) -> None:
    """Start `command`, wait until `workers_alive()` gives the pids of its 2 workers, kill -9 it, and
    assert every worker is gone within 5 s (killing any that is not, so no test leaves orphans)."""
    parent = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    pids: list[int] = []
    try:
        pids = _wait_for(lambda: parent.poll() is None and workers_alive(parent.pid), timeout, "two live workers")
        assert len(pids) == 2
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        try:
            _wait_for(lambda: all(_gone(p) for p in pids), 5.0, "the workers to die with their parent")
        except AssertionError:
            pytest.fail(f"workers {[p for p in pids if not _gone(p)]} outlived their parent")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(10)
        for pid in pids:
            if not _gone(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("mode", ["prctl", "watchdog"])
def test_spawned_workers_die_when_the_parent_is_killed(tmp_path, mode):
    if mode == "prctl" and not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux only")

    def busy(_parent_pid: int) -> list[int]:  # both workers past their initializer, running a task
        found = [int(p.name) for p in tmp_path.iterdir()]
        return found if len(found) == 2 else []

    kill_parent_and_check_workers([sys.executable, "-c", POOL, str(tmp_path), mode], busy)


def test_a_worker_whose_parent_already_died_exits_at_once():
    """The parent may die between spawn and prctl: the worker then sees another parent and exits."""
    code = "from pipeline.workers import die_with_parent; die_with_parent(1 if __import__('os').getppid() != 1 else 2)"
    done = subprocess.run([sys.executable, "-c", code + "; print('still here')"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 1 and "still here" not in done.stdout


def test_a_worker_whose_parent_lives_goes_on():
    code = "import os; from pipeline.workers import die_with_parent; die_with_parent(os.getppid()); print('ok')"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
