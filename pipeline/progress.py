"""Progress bars that suit both a terminal and a log file.

On a terminal tqdm redraws a line in place; in a CI log or a `dvc repro` capture every redraw is a
new line, so away from a TTY the bar refreshes at most every 30 s (and always at the end).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any


def progress_bar(iterable: Iterable | None = None, *, desc: str, unit: str, enabled: bool = True,
                 total: int | None = None, leave: bool = True) -> Any:
    from tqdm import tqdm

    interactive = sys.stderr.isatty()
    return tqdm(iterable, desc=desc, unit=unit, total=total, leave=leave, disable=not enabled,
                mininterval=0.1 if interactive else 30.0, dynamic_ncols=interactive)
