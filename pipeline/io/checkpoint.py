"""Resumable training checkpoints: tensors and primitives only, tied to the training that wrote them.

A checkpoint carries a fingerprint of what it was trained on (settings and data); a rerun resumes it
only when its own fingerprint matches. Another training's checkpoint is refused (it must never be
continued silently), or discarded with `force`. Loading never unpickles objects (`weights_only`).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import SitelocError


def resume_state(path: Path, fingerprint: str, *, force: bool, error: type[SitelocError] = SitelocError,
                 what: str = "other settings or data") -> dict | None:
    """The checkpoint at `path` when it belongs to this training, else None (none there, or another's with
    `force`); another's without `force` raises `error`."""
    import torch

    path = Path(path)
    if not path.is_file():
        return None
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if ckpt.get("fingerprint") == fingerprint:
        return ckpt
    if force:
        return None
    raise error(f"{path}: a checkpoint of another training ({what}); rerun with the settings it was made with "
                "to resume it, or --force to discard it and start afresh")


def save_checkpoint(path: Path, state: dict, fingerprint: str) -> None:
    """Write `state` (tensors and primitives) with the fingerprint, atomically."""
    import torch

    from pipeline.io.atomic import atomic_file

    with atomic_file(Path(path), "wb") as fh:
        torch.save({**state, "fingerprint": fingerprint}, fh)
