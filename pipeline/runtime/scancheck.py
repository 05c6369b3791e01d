"""Checking retrieved poses against the current laser scan before particles go there.

Retrieval hands the filter four poses; on a quasi-symmetric floor the right place is often ranked
fifth or twentieth (office: recall@4 0.46, recall@50 0.74), so four poses waste the injection on twins
while the truth sits further down the list. The scan that comes with the same update can tell many of
them apart: each of the Top-N retrieved poses is perturbed (`samples` poses around it, Gaussian, kept
in free space; then again around the best so far at half the spread, `rounds` times), every
perturbation is scored by a sensor model (`filter.scan_check.model`: by default the beam model, which
takes a person in front of the laser for a short reading where the filter's likelihood field scores a
miss; or the filter's own), and a candidate's score is its best
perturbation's log-likelihood (plus a prior from its retrieval rank, when given). The best `keep`
candidates, at their best-fitting pose, are what gets injected (weighted 4:3:2:1 as before). The
filter still decides between them over the next updates: a scan that fits a twin as well as the truth
leaves both in.

This is retrieval followed by geometric verification (place-recognition practice) with a laser
likelihood as the verifier; the cost is `rounds` sensor evaluations of N x samples poses, once per
injection.
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
                     std_xy: float, std_theta, rng: np.random.Generator,
                     log_prior: np.ndarray | None = None, rounds: int = 1) -> CheckedCandidates | None:
    """The `keep` retrieved poses (N, 3+) whose neighbourhood fits `scan` best (`std_theta`: one heading
    spread, radians, or one per pose); None when the scan has no usable beam (then retrieval's own order
    is all there is).

    With `rounds` > 1 each round draws `samples` poses around every candidate's best pose so far at half
    the previous spread (the best so far is one of them, so a score never falls): the scan's likelihood
    peaks within a few cm and degrees of the true pose, and one round of 0.5 m draws rarely lands there,
    while along a corridor, where a scan fits a whole line of poses, it always does; without refinement
    the wrong corridor outscores the right junction. With `log_prior` (N,), the order is by fit plus
    prior (a posterior up to a constant): a twin that fits the scan as well as the right place no longer
    wins by a hair of laser noise."""
    centres = np.asarray(retrieved, dtype=np.float64)[:, :3]
    n = len(centres)
    if n == 0:
        raise ValueError("no retrieved poses to check")
    which = np.repeat(np.arange(n), samples)
    std_theta = np.broadcast_to(np.asarray(std_theta, dtype=np.float64), (n,))
    best_pose, rel = centres, None
    for r in range(max(1, rounds)):
        scale = 0.5 ** r
        poses = lmap.jitter(best_pose[which], std_xy * scale, std_theta[which] * scale, rng)
        poses[::samples] = best_pose  # the retrieved pose (then the best so far) is always one of them
        res = sensor.evaluate(poses, scan)
        if res.beams_used == 0:
            return None
        ll = res.log_likelihood.reshape(n, samples)
        best = np.argmax(ll, axis=1)
        flat = np.arange(n) * samples + best
        best_pose, score, rel = poses[flat], ll[np.arange(n), best], res.relative_likelihood[flat]
    rank_by = score if log_prior is None else score + np.asarray(log_prior, dtype=np.float64)
    # Ties (identical fits, e.g. no beam hit anything) keep retrieval's order.
    order = np.lexsort((np.arange(n), -rank_by))[: min(keep, n)]
    return CheckedCandidates(best_pose[order], order, score[order], rel[order])
