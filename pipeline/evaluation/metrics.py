"""Localization metrics of one replay: convergence, losing track after it, accuracy, kidnap recovery.

"Converged at s" means the position error stays below `threshold_m` for `hold` consecutive steps from s
(or to the end of the run when fewer remain). "Lost track at s" is the mirror image: after convergence,
outside the kidnapped intervals, the error stays at or above the threshold for `hold` steps from s (or
to the end of its segment). A replay is *held* when it converged and never lost track; a filter that
converges at step 0 and then walks away is not. Accuracy is measured over every step from the first
convergence on, minus each kidnapping's interval until it recovers (lost-track steps count), and over
all steps. A kidnapping's final error is the median error over the last `hold` steps before the next
one (or the end), counting only steps from its recovery on. The full definitions: docs/evaluation.md.
"""

from __future__ import annotations

import numpy as np


def _runs_of(ok: np.ndarray) -> np.ndarray:
    """run[i] = length of the run of True values starting at i (run[n] = 0)."""
    n = len(ok)
    run = np.zeros(n + 1, dtype=np.int64)
    for i in range(n - 1, -1, -1):
        run[i] = run[i + 1] + 1 if ok[i] else 0
    return run


def first_settled(errors: np.ndarray, start: int, threshold_m: float, hold: int) -> int | None:
    """First step s >= start from which errors stay under the threshold for `hold` steps (or to the end)."""
    ok = np.asarray(errors[start:]) < threshold_m
    n = len(ok)
    if n == 0:
        return None
    run = _runs_of(ok)
    need = np.minimum(hold, n - np.arange(n))
    hits = np.nonzero(run[:n] >= need)[0]
    return int(start + hits[0]) if len(hits) else None


def lost_track(errors: np.ndarray, tracked: np.ndarray, segment_end: np.ndarray, threshold_m: float,
               hold: int) -> list[tuple[int, int | None]]:
    """Each time a converged filter loses track: (step it lost track, step it settled again or None).

    `tracked[i]` says step i counts (converged, not inside a kidnapping's search); `segment_end[i]` is
    where step i's stretch ends (the next kidnapping or the end). Lost at s: errors >= threshold on
    tracked steps s..s+hold-1 (fewer when the segment ends first), the first such s after a settled step."""
    errors = np.asarray(errors, dtype=np.float64)
    n = len(errors)
    bad = _runs_of(tracked & (errors >= threshold_m))
    starts = np.nonzero(tracked & (bad[:n] >= np.minimum(hold, segment_end - np.arange(n))))[0]
    out: list[tuple[int, int | None]] = []
    s = 0
    while s < n:
        k = int(np.searchsorted(starts, s))
        if k == len(starts):
            break
        lost = int(starts[k])
        back = first_settled(errors[: segment_end[lost]], lost, threshold_m, hold)
        out.append((lost, back))
        if back is None:  # lost to the end of the segment: a kidnapping after it starts afresh
            s = int(segment_end[lost])
            continue
        s = back
    return out


def replay_metrics(errors: np.ndarray, kidnaps: list[int], particles: np.ndarray, update_ms: np.ndarray,
                   updated: np.ndarray, threshold_m: float = 0.5, hold: int = 10) -> dict:
    errors = np.asarray(errors, dtype=np.float64)
    n = len(errors)
    converged = first_settled(errors, 0, threshold_m, hold)
    mask = np.zeros(n, bool)
    recoveries, finals = [], []
    if converged is not None:
        mask[converged:] = True
    for i, k in enumerate(kidnaps):
        back = first_settled(errors, k, threshold_m, hold)
        recoveries.append(None if back is None else back - k)
        mask[k: (back if back is not None else n)] = False
        # Where the filter ends up before the next kidnapping: the median of that segment's last `hold` steps,
        # from the recovery on (a kidnapping a few steps before the end must not count its search as final).
        end = kidnaps[i + 1] if i + 1 < len(kidnaps) else n
        start = max(k if back is None else back, end - hold)
        finals.append(round(float(np.median(errors[start:end])), 4) if end > start else None)
    segment_end = np.full(n, n, dtype=np.int64)
    for k in sorted(kidnaps, reverse=True):
        segment_end[:k] = k
    losses = lost_track(errors, mask, segment_end, threshold_m, hold) if converged is not None else []
    good = errors[mask]
    ms = np.asarray(update_ms)[np.asarray(updated, bool)]

    def stat(f, a):
        return round(float(f(a)), 4) if len(a) else None

    return {
        "steps": int(n),
        "converged_step": converged,
        "lost_track_steps": [int(s) for s, _ in losses],
        "regained_steps": [None if b is None else int(b) for _, b in losses],
        "held": converged is not None and not losses,
        "within_threshold_share": stat(np.mean, good < threshold_m),
        "error_median_m": stat(np.median, good),
        "error_mean_m": stat(np.mean, good),
        "error_p90_m": stat(lambda a: np.percentile(a, 90), good),
        "error_median_all_m": stat(np.median, errors),
        "kidnaps": [int(k) for k in kidnaps],
        "recovery_steps": recoveries,
        "recovered": int(sum(r is not None for r in recoveries)),
        "recovery_final_error_m": finals,
        "particles_mean": stat(np.mean, np.asarray(particles)),
        "particles_max": int(np.max(particles)) if len(particles) else 0,
        "update_ms_mean": stat(np.mean, ms),
        "update_ms_p90": stat(lambda a: np.percentile(a, 90), ms),
    }
