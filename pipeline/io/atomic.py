"""Write-then-rename helpers: an interrupted step never leaves a half-written output behind."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from pipeline.errors import OutputExistsError, OutputOverlapsInputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publishable(path: str | Path, mode: int) -> None:
    """mkstemp/mkdtemp create owner-only entries; give the final output the usual umask permissions."""
    os.chmod(path, mode & ~_umask())


@contextlib.contextmanager
def atomic_file(path: Path, mode: str = "wb") -> Iterator:
    """Open a temporary sibling of `path`; rename it over `path` only if the block completes."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp-write", dir=path.parent)
    _publishable(tmp, 0o666)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: Path, text: str) -> Path:
    with atomic_file(path, "w") as fh:
        fh.write(text)
    return Path(path)


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    with atomic_file(path, "wb") as fh:
        fh.write(data)
    return Path(path)


def _flat(inputs) -> Iterator[Path | str]:
    for item in inputs:
        if isinstance(item, list | tuple | set | frozenset):
            yield from _flat(item)
        elif isinstance(item, str | os.PathLike):
            yield item


def refuse_overlap(out: Path, inputs: Iterable[Path | str | None]) -> None:
    """OutputOverlapsInputError when `out` is, is inside, or contains one of `inputs`.

    `--force` replaces the output directory as a whole, so an output that overlaps an input would
    destroy it (or leave a site with a foreign folder inside); links are resolved first.
    """
    target = Path(out).expanduser().resolve()
    for given in _flat(inputs):
        source = Path(given).expanduser().resolve()
        if target == source:
            how = "is the input"
        elif target.is_relative_to(source):
            how = "is inside the input"
        elif source.is_relative_to(target):
            how = "contains the input"
        else:
            continue
        raise OutputOverlapsInputError(
            f"output {out} {how} {given}; writing it would replace or alter that input. Nothing was written: "
            f"give --out a separate path (e.g. beside the input, not in it)")


def check_output(out: Path, *, force: bool, inputs: Iterable[Path | str | None]) -> None:
    """What a stage checks before it starts work: the output does not overlap an input and, without
    `force`, does not exist yet."""
    refuse_overlap(out, inputs)
    if Path(out).exists() and not force:
        raise OutputExistsError(Path(out))


@contextlib.contextmanager
def atomic_dir(out: Path, *, force: bool = False, inputs: Iterable[Path | str | None]) -> Iterator[Path]:
    """Yield a temporary directory beside `out`; it becomes `out` only when the block completes.

    With `force`, an existing `out` is moved aside first and deleted only after the new one is in
    place, so an interruption at any moment leaves either the old or the new output, never a mix.
    Leftover temporaries from an interrupted earlier run are removed. `inputs` are the paths the step
    reads: an `out` that overlaps one of them is refused before anything is touched.
    """
    out = Path(out)
    check_output(out, force=force, inputs=inputs)
    out.parent.mkdir(parents=True, exist_ok=True)
    for stale in out.parent.glob(f".{out.name}.tmp-*"):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    _publishable(tmp, 0o777)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.tmp-old"
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
