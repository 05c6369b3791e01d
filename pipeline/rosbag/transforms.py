"""A tf buffer for recorded transforms: time-stamped SE(3) edges, interpolated, chained along the tree.

Lookups are vectorised over many stamps. A dynamic edge is interpolated between the two samples around a
stamp (translation linearly, rotation by slerp, as tf2 does) when they are at most `max_gap` seconds
apart; a stamp in a longer gap or outside the recorded span (beyond `tolerance`) gets no transform, so
the caller can report it. Poses are named by their frames: `lookup("map", "base_link", t)` is map_from_base.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class Transforms:
    """N rigid transforms parent_from_child: rotations `rot` and translations `xyz` (N, 3); `valid` (N,)."""

    rot: Rotation
    xyz: np.ndarray
    valid: np.ndarray

    def __mul__(self, other: Transforms) -> Transforms:
        return Transforms(self.rot * other.rot, self.rot.apply(other.xyz) + self.xyz, self.valid & other.valid)

    def inv(self) -> Transforms:
        r = self.rot.inv()
        return Transforms(r, -r.apply(self.xyz), self.valid.copy())

    def floor_pose(self, axis: int = 0) -> np.ndarray:
        """(N, 3) x, y, heading on the floor: heading of the child's `axis` (0 = x for a base, 2 = z for an
        optical frame) projected on the parent's x-y plane."""
        m = self.rot.as_matrix()[:, :, axis]
        return np.column_stack([self.xyz[:, 0], self.xyz[:, 1], np.arctan2(m[:, 1], m[:, 0])])


def from_floor_pose(poses: np.ndarray, z: float = 0.0) -> Transforms:
    """SE(2) poses (N, 3) as SE(3) transforms at height z."""
    poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    rot = Rotation.from_euler("z", poses[:, 2:3])  # (N, 1): N rotations (scipy 1.17 rejects a 1-D array here)
    xyz = np.column_stack([poses[:, :2], np.full(len(poses), z)])
    return Transforms(rot, xyz, np.ones(len(poses), bool))


@dataclass
class Edge:
    """One parent -> child edge's transforms, kept in flat float arrays (8 bytes a number, not a Python object:
    a long recording's tf is hundreds of thousands of transforms)."""

    parent: str
    child: str
    static: bool
    stamps: array = field(default_factory=lambda: array("d"))
    xyz: array = field(default_factory=lambda: array("d"))  # x, y, z per transform
    quat: array = field(default_factory=lambda: array("d"))  # x, y, z, w per transform

    def __len__(self) -> int:
        return len(self.stamps)

    def add(self, stamp: float, xyz, quat) -> None:
        self.stamps.append(stamp)
        self.xyz.extend(xyz)
        self.quat.extend(quat)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.array(self.stamps, dtype=np.float64)  # copies: the arrays stay free to grow
        order = np.argsort(t, kind="stable")
        xyz = np.array(self.xyz, dtype=np.float64).reshape(-1, 3)
        quat = np.array(self.quat, dtype=np.float64).reshape(-1, 4)
        return t[order], xyz[order], quat[order]


class TfBuffer:
    """Every transform of a recording, by child frame (a tf tree: one parent per child)."""

    def __init__(self, max_gap: float = 0.5, tolerance: float = 0.05):
        self.max_gap, self.tolerance = float(max_gap), float(tolerance)
        self.edges: dict[str, Edge] = {}
        self._cache: dict[str, tuple] = {}

    def add(self, parent: str, child: str, stamp: float, xyz, quat, *, static: bool) -> str | None:
        """Record one transform; returns a problem text when `child` already has another parent."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        edge = self.edges.get(child)
        if edge is None:
            edge = self.edges[child] = Edge(parent, child, static)
        elif edge.parent != parent:
            return f"frame '{child}' has two parents, '{edge.parent}' and '{parent}'"
        if static:
            edge.static = True
            edge.stamps, edge.xyz, edge.quat = array("d", [stamp]), array("d", xyz), array("d", quat)
        else:
            edge.add(stamp, xyz, quat)
        self._cache.pop(child, None)
        return None

    def frames(self) -> set[str]:
        return set(self.edges) | {e.parent for e in self.edges.values()}

    def chain(self, child: str) -> list[str]:
        """Frames from `child` up to the root of its tree."""
        out = [child]
        while out[-1] in self.edges and len(out) <= len(self.edges):
            out.append(self.edges[out[-1]].parent)
        return out

    def path(self, parent: str, child: str) -> tuple[list[str], list[str]] | None:
        """(up, down): child -> common ancestor, ancestor -> parent; None when they are not connected."""
        up, down = self.chain(child), self.chain(parent)
        common = next((f for f in up if f in down), None)
        if common is None:
            return None
        return up[: up.index(common) + 1], down[: down.index(common) + 1]

    def edge_at(self, child: str, stamps: np.ndarray) -> Transforms:
        """parent_from_child of one edge at `stamps`, interpolated; invalid in gaps and outside its span."""
        e = self.edges[child]
        if child not in self._cache:
            self._cache[child] = e.arrays()
        t, xyz, quat = self._cache[child]
        n = len(stamps)
        if e.static:
            return Transforms(Rotation.from_quat(np.repeat(quat[:1], n, axis=0)), np.repeat(xyz[:1], n, axis=0),
                              np.ones(n, bool))
        hi = np.clip(np.searchsorted(t, stamps, side="left"), 0, len(t) - 1)
        lo = np.clip(hi - 1, 0, len(t) - 1)
        exact = np.isclose(t[hi], stamps, rtol=0, atol=1e-9)
        lo = np.where(exact, hi, lo)
        span = t[hi] - t[lo]
        inside = (stamps >= t[lo] - 1e-9) & (stamps <= t[hi] + 1e-9) & (span <= self.max_gap)
        before = stamps < t[0]
        after = stamps > t[-1]
        near_end = (before & (t[0] - stamps <= self.tolerance)) | (after & (stamps - t[-1] <= self.tolerance))
        valid = inside | near_end
        w = np.where(span > 0, (stamps - t[lo]) / np.where(span > 0, span, 1.0), 0.0)
        w = np.clip(w, 0.0, 1.0)
        pos = xyz[lo] + w[:, None] * (xyz[hi] - xyz[lo])
        r_lo, r_hi = Rotation.from_quat(quat[lo]), Rotation.from_quat(quat[hi])
        rot = r_lo * Rotation.from_rotvec((r_lo.inv() * r_hi).as_rotvec() * w[:, None])
        return Transforms(rot, pos, valid)

    def lookup(self, parent: str, child: str, stamps) -> Transforms:
        """parent_from_child at `stamps` through the tree; raises KeyError when the frames are not connected."""
        stamps = np.atleast_1d(np.asarray(stamps, dtype=np.float64))
        p = self.path(parent, child)
        if p is None:
            raise KeyError(f"no tf path from '{parent}' to '{child}'")
        up, down = p
        n = len(stamps)
        ident = Transforms(Rotation.identity(n), np.zeros((n, 3)), np.ones(n, bool))
        anc_from_child = ident
        for f in reversed(up[:-1]):  # ancestor ... -> child
            anc_from_child = anc_from_child * self.edge_at(f, stamps)
        anc_from_parent = ident
        for f in reversed(down[:-1]):
            anc_from_parent = anc_from_parent * self.edge_at(f, stamps)
        return anc_from_parent.inv() * anc_from_child

    def gaps(self, child: str, min_gap: float | None = None) -> list[tuple[float, float]]:
        """(start, end) stamps of the intervals longer than `max_gap` without a sample of a dynamic edge."""
        e = self.edges[child]
        if e.static:
            return []
        t = np.unique(np.array(e.stamps, dtype=np.float64))
        d = np.diff(t)
        limit = self.max_gap if min_gap is None else min_gap
        return [(float(t[i]), float(t[i + 1])) for i in np.nonzero(d > limit)[0]]
