"""Camera hypotheses held against the tracked belief, each with the evidence for it (docs/runtime.md).

A hypothesis is a pose far from the filter's estimate that a camera source proposed and the scan did
not rule out. At each check the estimate, the hypotheses so far (moved by odometry since) and the new
proposals are fitted to the scan alike (`scancheck.check_candidates`: each at its best-fitting pose, so
a converged cluster's precision is no advantage) and every far pose that fits well enough adds

    log(1 + rank(estimate)) - log(1 + rank(pose))  +  laser_nats if it fits better by `distinct` per beam

to its evidence (nats): the camera's log-likelihood ratio of it against the estimate (rank(x): of the
first ranked view near x; a Zipf model of retrieval's precision), plus the laser's when the scan tells
the two apart. A pose that fits worse by `distinct` per beam, or whose evidence falls to zero, is
dropped. One whose evidence reaches the threshold after `min_checks` checks has won. The same rule
covers a twin the laser cannot tell from the truth (the camera decides, slowly) and a kidnapping the
laser sees before its kidnap rule fires (the scan decides, quickly).
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True)
class Weighing:
    """How hypotheses are weighed (`filter.camera`, with the scan check's draws)."""

    pool: int  # the first `pool` ranked poses are new proposals
    samples: int
    rounds: int
    std_xy: float
    std_theta: float  # radians
    min_distance_m: float
    distinct: float  # per-beam log-likelihood difference at which the laser tells two poses apart
    laser_nats: float
    min_fit: float  # per-beam relative likelihood a hypothesis must reach in itself
    radius_m: float
    heading_rad: float
    max_rank: int | None
    min_checks: int


class Hypotheses:
    """Far poses that fit the scan, each with its evidence against the estimate (nats) and checks."""

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

    def check(self, sensor, lmap: LaserMap, estimate, ranked: np.ndarray, scan, how: Weighing, *, threshold: float,
              rng: np.random.Generator) -> np.ndarray | None:
        """The pose (3,) of a hypothesis that has won at this check (the list is then cleared), or None.

        `ranked`: the camera's ranked poses, best first (all of them rank the hypotheses; the first
        `how.pool` are new proposals)."""
        estimate = np.asarray(estimate, dtype=np.float64)[:3]
        ranked = np.asarray(ranked, dtype=np.float64)[:, :3]
        m = len(self.poses)
        cands = np.vstack([estimate[None], self.poses, ranked[:how.pool]])
        got = check_candidates(sensor, lmap, cands, scan, keep=len(cands), samples=how.samples, std_xy=how.std_xy,
                               std_theta=how.std_theta, rng=rng, rounds=how.rounds)
        if got is None:
            return None
        beams = max(sensor.beams(scan)[0].size, 1)
        rank = rank_near(got.poses, ranked, radius_m=how.radius_m, heading_rad=how.heading_rad)
        camera_ll = -np.log1p(rank if how.max_rank is None else np.minimum(rank, how.max_rank))
        own = got.rank == 0
        own_ll, own_camera = float(got.log_likelihood[own][0]), float(camera_ll[own][0])
        per_beam = (got.log_likelihood - own_ll) / beams
        far = np.hypot(*(got.poses[:, :2] - estimate[:2]).T) >= how.min_distance_m
        fits = (per_beam >= -how.distinct) & (got.relative_likelihood >= how.min_fit)
        keep = far & fits & ~own
        held = np.zeros(len(cands))
        held[1:m + 1] = self.evidence
        seen = np.zeros(len(cands), dtype=np.int64)
        seen[1:m + 1] = self.checks
        gain = camera_ll - own_camera + how.laser_nats * (per_beam > how.distinct)
        # Hypotheses first (most evidence first), then new poses by gain then fit: a pose near one kept
        # already is that one, so a hypothesis keeps its evidence when a proposal lands beside it.
        idx = np.nonzero(keep)[0]
        order = idx[np.lexsort((-got.log_likelihood[idx], -gain[idx], got.rank[idx] > m, -held[got.rank[idx]]))]
        poses, evidence, checks = [], [], []
        for i in order:
            pose = got.poses[i]
            if any(np.hypot(*(pose[:2] - p[:2])) < 2 * how.std_xy for p in poses):
                continue
            total = held[got.rank[i]] + gain[i]
            if total <= 0:
                continue  # nothing prefers it to the estimate: not worth following
            poses.append(pose)
            evidence.append(total)
            checks.append(seen[got.rank[i]] + 1)
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        self.evidence = np.asarray(evidence, dtype=np.float64)
        self.checks = np.asarray(checks, dtype=np.int64)
        won = np.nonzero((self.evidence >= threshold) & (self.checks >= how.min_checks))[0]
        if not len(won):
            return None
        best = self.poses[won[np.argmax(self.evidence[won])]].copy()
        self.clear()
        return best
