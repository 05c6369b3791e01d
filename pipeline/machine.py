"""What machine a figure was measured on: printed by benchmarks/ and recorded beside timed outputs."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def usable_cores() -> int | str:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"


def usable_core_count() -> int:
    """The cores this process may run on (the affinity mask where the OS has one, else the CPU count):
    how many workers a stage starts."""
    cores = usable_cores()
    return cores if isinstance(cores, int) else (os.cpu_count() or 1)


def machine_info() -> list[str]:
    """Lines for a benchmark's header: platform, CPU, cores, Python and numpy versions."""
    import numpy as np

    return [
        f"platform: {platform.platform()}",
        f"cpu: {cpu_model()}",
        f"cpu count: {os.cpu_count()} (usable: {usable_cores()})",
        f"python: {platform.python_version()}  numpy: {np.__version__}",
    ]


def machine_summary() -> str:
    """One line: CPU, usable cores, OS."""
    return f"{cpu_model()}, {usable_cores()} usable cores, {platform.system()}"


def median_ms(fn, repeat: int) -> float:
    """Median wall time of `repeat` calls of `fn`, in milliseconds (benchmarks' per-call figures)."""
    import statistics
    import time

    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)
