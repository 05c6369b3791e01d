"""Localization metrics of one replay: convergence, accuracy after it, recovery after each kidnapping.

"Converged at s" means the position error stays below `threshold_m` for `hold` consecutive steps from s
(or to the end of the run when fewer remain). Accuracy is measured over the steps where the filter is
converged: from the first convergence on, minus each kidnapping's interval until it recovers. A
kidnapping's final error is the median error over the last `hold` steps before the next one (or the end),
counting only steps from its recovery on.
"""

from __future__ import annotations

import numpy as np


def first_settled(errors: np.ndarray, start: int, threshold_m: float, hold: int) -> int | None:
    """First step s >= start from which errors stay under the threshold for `hold` steps (or to the end)."""
    ok = np.asarray(errors[start:]) < threshold_m
    n = len(ok)
    if n == 0:
        return None
    # run[i] = length of the run of True values starting at i
    run = np.zeros(n + 1, dtype=np.int64)
    for i in range(n - 1, -1, -1):
        run[i] = run[i + 1] + 1 if ok[i] else 0
    need = np.minimum(hold, n - np.arange(n))
    hits = np.nonzero(run[:n] >= need)[0]
    return int(start + hits[0]) if len(hits) else None


def replay_metrics(errors: np.ndarray, kidnaps: list[int], particles: np.ndarray, update_ms: np.ndarray,
                   updated: np.ndarray, threshold_m: float = 0.5, hold: int = 10) -> dict:
    errors = np.asarray(errors, dtype=np.float64)
    converged = first_settled(errors, 0, threshold_m, hold)
    mask = np.zeros(len(errors), bool)
    recoveries, finals = [], []
    if converged is not None:
        mask[converged:] = True
    for i, k in enumerate(kidnaps):
        back = first_settled(errors, k, threshold_m, hold)
        recoveries.append(None if back is None else back - k)
        mask[k: (back if back is not None else len(errors))] = False
        # Where the filter ends up before the next kidnapping: the median of that segment's last `hold` steps,
        # from the recovery on (a kidnapping a few steps before the end must not count its search as final).
        end = kidnaps[i + 1] if i + 1 < len(kidnaps) else len(errors)
        start = max(k if back is None else back, end - hold)
        finals.append(round(float(np.median(errors[start:end])), 4) if end > start else None)
    good = errors[mask]
    ms = np.asarray(update_ms)[np.asarray(updated, bool)]

    def stat(f, a):
        return round(float(f(a)), 4) if len(a) else None

    return {
        "steps": int(len(errors)),
        "converged_step": converged,
        "error_median_m": stat(np.median, good),
        "error_mean_m": stat(np.mean, good),
        "error_p90_m": stat(lambda a: np.percentile(a, 90), good),
        "kidnaps": [int(k) for k in kidnaps],
        "recovery_steps": recoveries,
        "recovered": int(sum(r is not None for r in recoveries)),
        "recovery_final_error_m": finals,
        "particles_mean": stat(np.mean, np.asarray(particles)),
        "particles_max": int(np.max(particles)) if len(particles) else 0,
        "update_ms_mean": stat(np.mean, ms),
        "update_ms_p90": stat(lambda a: np.percentile(a, 90), ms),
    }
