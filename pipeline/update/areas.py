"""Areas of a site database: which old stops a new capture replaces, and which map cells an area owns.

An area is the unit a mapping team re-captures. A stop's area key is `room/area` from its labels,
`room` when it has only a room, and `stop:<stop_id>` when it has none (an unlabelled stop is its own
area). A new stop keeps its labels; an unlabelled one takes the area of the nearest old stop within
`proximity_m`. The cells of an area are those whose nearest stop, along the free space, belongs to it
(a geodesic Voronoi partition of the map), so every cell has exactly one owner, a room's cells stay with
the room's stops, and a patch stays inside its areas.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from pipeline.errors import Problems
from pipeline.io.map_yaml import OccupancyMap


@dataclass(frozen=True)
class Stops:
    """One row per stop of an images table: its id, position and labels, in first-appearance order."""

    stop_id: list[str]
    xy: np.ndarray  # (N, 2) map frame, metres
    room: list[str | None]
    area: list[str | None]

    def key(self, i: int) -> str:
        return area_key(self.room[i], self.area[i], self.stop_id[i])

    def keys(self) -> list[str]:
        return [self.key(i) for i in range(len(self.stop_id))]


def area_key(room: str | None, area: str | None, stop_id: str) -> str:
    if room and area:
        return f"{room}/{area}"
    if room:
        return room
    return f"stop:{stop_id}"


def stops_of(images: pa.Table) -> Stops:
    """The stops of an `images` table (views of a stop share its position and labels)."""
    cols = images.select(["stop_id", "x", "y", "room", "area"]).to_pydict()
    first: dict[str, int] = {}
    for i, s in enumerate(cols["stop_id"]):
        first.setdefault(s, i)
    rows = list(first.values())
    return Stops(
        stop_id=[cols["stop_id"][i] for i in rows],
        xy=np.array([[cols["x"][i], cols["y"][i]] for i in rows], dtype=np.float64).reshape(-1, 2),
        room=[cols["room"][i] for i in rows],
        area=[cols["area"][i] for i in rows],
    )


def assign_areas(old: Stops, new: Stops, *, proximity_m: float, allow_new_areas: bool, where: str,
                 problems: Problems) -> dict[str, tuple[str, str | None, str | None]]:
    """{new stop_id: (area key, room, area)}; each new stop's area, by label or by the nearest old stop.

    A labelled area the old database does not have is a problem unless `allow_new_areas`; an unlabelled
    stop farther than `proximity_m` from every old stop is a problem. Problems name `where` and the stop."""
    old_keys = old.keys()
    known = set(old_keys)
    known_rooms = {r for r in old.room if r}
    out: dict[str, tuple[str, str | None, str | None]] = {}
    for i, sid in enumerate(new.stop_id):
        room, area = new.room[i], new.area[i]
        if room:
            key = area_key(room, area, sid)
            if key not in known and not allow_new_areas:
                what = f"area '{key}'" if area else f"room '{room}'"
                hint = f"; the database's areas of room '{room}' are " + ", ".join(
                    sorted(k for k in known if k.startswith(f"{room}/") or k == room)) if room in known_rooms else ""
                problems.add(where, f"stop '{sid}' is labelled with {what}, which the site database does not "
                             f"have{hint}", fix="label it with an existing room/area, leave room and area empty to "
                             "place it by proximity, or pass --allow-new-areas for a new part of the building")
            out[sid] = (key, room, area)
            continue
        if len(old.stop_id) == 0:
            problems.add(where, f"stop '{sid}' has no room/area label and the site database has no stops to "
                         "place it by", fix="label it")
            continue
        d = np.hypot(*(old.xy - new.xy[i]).T)
        j = int(np.argmin(d))
        if d[j] > proximity_m:
            problems.add(where, f"stop '{sid}' at ({new.xy[i, 0]:.2f}, {new.xy[i, 1]:.2f}) has no room/area label "
                         f"and no old stop within update.proximity_m = {proximity_m:g} m (the nearest, "
                         f"'{old.stop_id[j]}', is {d[j]:.2f} m away)",
                         fix="label it with a room/area, or raise update.proximity_m")
            continue
        out[sid] = (old_keys[j], old.room[j], old.area[j])
    return out


def cell_owners(occ_map: OccupancyMap, xy: np.ndarray, keys: list[str]) -> tuple[np.ndarray, list[str]]:
    """(owner index per cell (H, W), the area keys it indexes): each cell belongs to the area of the stop
    nearest to it along the free space, so a room's cells never go to a stop behind its wall.

    Free cells are a graph (8-neighbours, diagonal steps only between two free orthogonal neighbours, so
    no path slips through a wall's corner); scipy's multi-source Dijkstra gives each its nearest stop.
    Occupied, unknown and unreached cells take the owner of the nearest free cell that has one, so each
    face of a wall belongs to the room it faces.
    """
    from scipy.ndimage import distance_transform_edt
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    names = sorted(set(keys))
    stop_area = np.array([names.index(k) for k in keys], dtype=np.int64)
    h, w = occ_map.height, occ_map.width
    passable = occ_map.free.copy()
    row, col = occ_map.world_to_cell(np.asarray(xy)[:, 0], np.asarray(xy)[:, 1])
    inside = occ_map.contains(row, col)
    passable[row[inside], col[inside]] = True  # a stop is a source even on a cell the map does not call free
    node = np.full((h, w), -1, dtype=np.int64)
    node[passable] = np.arange(int(passable.sum()))
    pad, pad_node = np.pad(passable, 1), np.pad(node, 1, constant_values=-1)

    def shifted(arr, dr, dc):  # arr[r + dr, c + dc] for every cell (r, c), padding outside
        return arr[1 + dr: h + 1 + dr, 1 + dc: w + 1 + dc]

    a, b, weight = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ok = passable & shifted(pad, dr, dc)
        if dr and dc:  # diagonal: both orthogonal neighbours free too
            ok &= shifted(pad, dr, 0) & shifted(pad, 0, dc)
        a.append(node[ok])
        b.append(shifted(pad_node, dr, dc)[ok])
        weight.append(np.full(int(ok.sum()), np.hypot(dr, dc)))
    n = int(passable.sum())
    graph = coo_matrix((np.concatenate(weight), (np.concatenate(a), np.concatenate(b))), shape=(n, n)).tocsr()
    first = {}
    for i in np.flatnonzero(inside):  # stops on one cell: the first one's area
        first.setdefault(int(node[row[i], col[i]]), i)
    sources = np.array(sorted(first), dtype=np.int64)
    owner = np.full((h, w), -1, dtype=np.int64)
    if len(sources):
        _, _, reached_from = dijkstra(graph, directed=False, indices=sources, min_only=True,
                                      return_predecessors=True)
        label = np.full(n, -1, dtype=np.int64)
        ok = reached_from >= 0
        label[ok] = stop_area[[first[int(s)] for s in reached_from[ok]]]
        owner[passable] = label
    if (owner < 0).all():  # no stop on the map: every cell to the nearest stop in the plane
        from scipy.spatial import cKDTree

        rr, cc = np.indices((h, w))
        x, y = occ_map.cell_to_world(rr.ravel(), cc.ravel())
        _, nearest = cKDTree(np.asarray(xy, dtype=np.float64)).query(np.column_stack([x, y]))
        return stop_area[nearest].reshape(h, w), names
    _, (near_r, near_c) = distance_transform_edt(owner < 0, return_indices=True)
    return owner[near_r, near_c], names
