"""The camera as evidence between hypotheses the laser cannot tell apart (`filter.evidence`).

On a quasi-symmetric floor a wrong twin of the place fits every scan as well as the truth: after a
kidnapping the filter can settle on one (office query_03@119: five twins 5 to 34 m away fit the laser
as well as the truth, the one the filter holds slightly better, update after update), and the
challenge (`scancheck.Rivals`), which needs a rival to fit the scan better, never fires. What tells
them apart is the camera, slowly: the truth's database views keep being ranked higher than the
twin's (over 12 frames the truth's summed log(1 + rank) was 6.3, the twin's 13.2). Put into the
particle weights that difference is too weak to pull the filter off its cluster, which fits each scan
a little better because its particles sit on the laser's peak, while freshly injected ones do not
(docs/evaluation.md, 2026-12-02).

So the evidence is kept per hypothesis, not per particle. At each check the image's Top-N, the
hypotheses so far (moved by odometry) and the estimate are checked against the scan alike
(`check_candidates`: each at its best-fitting pose, so a converged cluster's precision is no
advantage). A far pose whose fit is within `tolerance` per beam of the estimate's, and good in
itself, adds the image's log-likelihood ratio of it against the estimate,

    log(1 + rank(estimate)) - log(1 + rank(pose)),   rank(x): of the first Top-N view near x (N if none)

(the Zipf model of retrieval's precision `scan_check.rank_prior` uses) to its evidence; one that fits
worse, or whose evidence falls to zero, is dropped. A hypothesis whose evidence reaches `threshold`
after at least `min_checks` checks has won: the belief is replaced by one around it, since injecting
particles beside the old cluster leaves the old cluster, on its peak, to take the belief back.
"""

from __future__ import annotations

import numpy as np

from pipeline.runtime.grid import LaserMap
from pipeline.runtime.scancheck import check_candidates


def rank_near(poses: np.ndarray, ranked: np.ndarray, *, radius_m: float, heading_rad: float) -> np.ndarray:
    """(N,) for each pose (N, 3+) the rank of the first of `ranked` (K, 3+; best first) within radius_m
    and heading_rad of it, or K when none is."""
    from pipeline.retrieval.metrics import positives

    poses = np.asarray(poses, dtype=np.float64)
    ranked = np.asarray(ranked, dtype=np.float64)
    k = len(ranked)
    if k == 0:
        return np.zeros(len(poses), dtype=np.int64)
    near = positives(poses, ranked, radius_m, np.degrees(heading_rad))  # retrieval's own "near"
    return np.where(near.any(axis=1), np.argmax(near, axis=1), k)


class ImageEvidence:
    """Hypotheses far from the estimate that fit the scan as well as it does, each with the image
    evidence for it accumulated over checks (log-likelihood ratio against the estimate, nats)."""

    def __init__(self):
        self.poses = np.zeros((0, 3))
        self.evidence = np.zeros(0)
        self.checks = np.zeros(0, dtype=np.int64)
        self.age = 0  # updates the filter has tracked its current estimate without a jump
        self._odom: np.ndarray | None = None
        self._estimate: np.ndarray | None = None

    def clear(self) -> None:
        self.poses, self.evidence, self.checks = np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)

    def follow(self, odom, estimate, *, tracking: bool, jump_m: float) -> None:
        """Apply the odometry since the last call to every hypothesis and to the last estimate, and age
        the belief: back to 0 while the filter is not tracking, or when its estimate is `jump_m` from
        where the odometry took the last one (it has moved to another hypothesis), else one older."""
        from pipeline.runtime.motion import compose_odometry, odometry_delta

        odom = np.asarray(odom, dtype=np.float64).reshape(3)
        estimate = np.asarray(estimate, dtype=np.float64)[:3]
        moved = self._estimate
        if self._odom is not None:
            delta = odometry_delta(self._odom, odom)
            if len(self.poses):
                self.poses = compose_odometry(self.poses, *delta)
            if moved is not None:
                moved = compose_odometry(moved[None], *delta)[0]
        jumped = moved is None or np.hypot(*(estimate[:2] - moved[:2])) >= jump_m
        self.age = 0 if (not tracking or jumped) else self.age + 1
        self._odom, self._estimate = odom, estimate

    def check(self, sensor, lmap: LaserMap, estimate, retrieved: np.ndarray, scan, *, pool: int, samples: int,
              std_xy: float, std_theta: float, min_distance_m: float, tolerance: float, min_fit: float,
              radius_m: float, heading_rad: float, max_rank: int | None = None, threshold: float, min_checks: int,
              rng: np.random.Generator, rounds: int = 1) -> np.ndarray | None:
        """The pose (3,) of a hypothesis that has won at this check (the list is then cleared), or None.

        `retrieved`: the image's ranked Top-N poses (all of them rank the hypotheses; the first `pool`
        are new candidates); `tolerance`: how much worse per beam (log-likelihood) than the estimate a
        hypothesis may fit; `min_fit`: the per-beam relative likelihood it must reach in itself."""
        estimate = np.asarray(estimate, dtype=np.float64)[:3]
        retrieved = np.asarray(retrieved, dtype=np.float64)[:, :3]
        m = len(self.poses)
        cands = np.vstack([estimate[None], self.poses, retrieved[:pool]])
        got = check_candidates(sensor, lmap, cands, scan, keep=len(cands), samples=samples, std_xy=std_xy,
                               std_theta=std_theta, rng=rng, rounds=rounds)
        if got is None:
            return None
        beams = max(sensor.beams(scan)[0].size, 1)
        rank = rank_near(got.poses, retrieved, radius_m=radius_m, heading_rad=heading_rad)
        image_ll = -np.log1p(rank if max_rank is None else np.minimum(rank, max_rank))
        own = got.rank == 0
        own_ll, own_image = float(got.log_likelihood[own][0]), float(image_ll[own][0])
        far = np.hypot(*(got.poses[:, :2] - estimate[:2]).T) >= min_distance_m
        fits = ((got.log_likelihood - own_ll) / beams >= -tolerance) & (got.relative_likelihood >= min_fit)
        keep = far & fits & ~own
        prior = np.zeros(len(cands))
        prior[1:m + 1] = self.evidence
        seen = np.zeros(len(cands), dtype=np.int64)
        seen[1:m + 1] = self.checks
        gain = image_ll - own_image
        # Hypotheses first (most evidence first), then new poses by image then fit: a pose near one kept
        # already is that one, so a hypothesis keeps its evidence when a retrieved pose lands beside it.
        idx = np.nonzero(keep)[0]
        order = idx[np.lexsort((-got.log_likelihood[idx], -gain[idx], got.rank[idx] > m,
                                -prior[got.rank[idx]]))]
        poses, evidence, checks = [], [], []
        for i in order:
            pose = got.poses[i]
            if any(np.hypot(*(pose[:2] - p[:2])) < 2 * std_xy for p in poses):
                continue
            total = prior[got.rank[i]] + gain[i]
            if total <= 0:
                continue  # the image does not prefer it to the estimate: not worth following
            poses.append(pose)
            evidence.append(total)
            checks.append(seen[got.rank[i]] + 1)
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        self.evidence = np.asarray(evidence, dtype=np.float64)
        self.checks = np.asarray(checks, dtype=np.int64)
        won = np.nonzero((self.evidence >= threshold) & (self.checks >= min_checks))[0]
        if not len(won):
            return None
        best = self.poses[won[np.argmax(self.evidence[won])]].copy()
        self.clear()
        return best
