"""Worker processes that die with their parent.

A spawned pool's workers outlive a parent killed with SIGKILL (its `atexit` and `finally` never run): render
workers of `synth --workers 2` kept holding cores and GPU memory after `kill -9`. Each pool's initializer
calls `die_with_parent(parent_pid)` first. On Linux the kernel then sends SIGKILL to the worker when its
parent dies (`prctl(PR_SET_PDEATHSIG)`); elsewhere a daemon thread polls the parent's pid. Either way a
parent that died before the worker got here (between spawn and prctl) is caught by comparing
`os.getppid()` with the pid the parent passed in.

Linux sends the signal when the *thread* that started the worker exits, so pools are fed (their workers
spawned) from the main thread, as `RenderPool` and `replay_in_processes` are.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
POLL_S = 0.5  # the watchdog thread's period where prctl is not available


def die_with_parent(parent_pid: int) -> None:
    """Make this process exit as soon as `parent_pid` (the process that started it) dies.

    Call it first in a worker's initializer, with `os.getpid()` taken in the parent (pass it in `initargs`).
    """
    if sys.platform.startswith("linux") and _pdeathsig(signal.SIGKILL):
        if os.getppid() != parent_pid:  # the parent died before prctl: no signal will come
            os._exit(1)
        return
    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=_watch, args=(parent_pid,), name="die-with-parent", daemon=True).start()


def _pdeathsig(sig: int) -> bool:
    """prctl(PR_SET_PDEATHSIG, sig) through libc; False if it cannot be set."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int) -> None:
    """Exit the process once it has been re-parented (its parent died)."""
    while os.getppid() == parent_pid:
        time.sleep(POLL_S)
    os._exit(1)
