"""Checking retrieved poses against the current laser scan before particles go there.

Retrieval hands the filter four poses; on a quasi-symmetric floor the right place is often ranked
fifth or twentieth (office: recall@4 0.46, recall@50 0.74), so four poses waste the injection on twins
while the truth sits further down the list. The scan that comes with the same update can tell many of
them apart: each of the Top-N retrieved poses is perturbed (`samples` poses around it, Gaussian, kept
in free space), every perturbation is scored by the filter's own sensor model, and a candidate's score
is its best perturbation's log-likelihood. The best `keep` candidates, at their best-fitting pose, are
what gets injected (weighted 4:3:2:1 as before). The filter still decides between them over the next
updates: a scan that fits a twin as well as the truth leaves both in.

This is retrieval followed by geometric verification (place-recognition practice) with the filter's
likelihood as the verifier; the cost is one sensor evaluation of N x samples poses, once per injection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.runtime.grid import LaserMap


@dataclass(frozen=True)
class CheckedCandidates:
    poses: np.ndarray  # (keep, 3) the best-fitting perturbation of each kept candidate, best first
    rank: np.ndarray  # (keep,) each kept candidate's rank in the retrieved list (0 = retrieval's Top-1)
    log_likelihood: np.ndarray  # (keep,) its best perturbation's scan log-likelihood
    relative_likelihood: np.ndarray  # (keep,) the same as the per-beam share of a perfect match's, (0, 1]


def check_candidates(sensor, lmap: LaserMap, retrieved: np.ndarray, scan, *, keep: int, samples: int,
                     std_xy: float, std_theta, rng: np.random.Generator) -> CheckedCandidates | None:
    """The `keep` retrieved poses (N, 3+) whose neighbourhood fits `scan` best (`std_theta`: one heading
    spread, radians, or one per pose); None when the scan has no usable beam (then retrieval's own order
    is all there is)."""
    centres = np.asarray(retrieved, dtype=np.float64)[:, :3]
    n = len(centres)
    if n == 0:
        raise ValueError("no retrieved poses to check")
    which = np.repeat(np.arange(n), samples)
    std_theta = np.broadcast_to(np.asarray(std_theta, dtype=np.float64), (n,))
    poses = lmap.jitter(centres[which], std_xy, std_theta[which], rng)
    poses[::samples] = centres  # the retrieved pose itself is always one of its perturbations
    res = sensor.evaluate(poses, scan)
    if res.beams_used == 0:
        return None
    ll = res.log_likelihood.reshape(n, samples)
    best = np.argmax(ll, axis=1)
    score = ll[np.arange(n), best]
    # Ties (identical fits, e.g. no beam hit anything) keep retrieval's order.
    order = np.lexsort((np.arange(n), -score))[: min(keep, n)]
    flat = order * samples + best[order]
    return CheckedCandidates(poses[flat], order, score[order], res.relative_likelihood[flat])
