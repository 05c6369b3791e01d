"""Areas: how new stops are placed in the old site's areas, and which area owns each map cell."""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest

from pipeline.errors import Problems
from pipeline.io.map_yaml import OCCUPIED
from pipeline.update.areas import Stops, area_key, assign_areas, cell_owners
from tests.fixtures.capture_site import RES, STOPS, floor_map

OLD = Stops(stop_id=[s[0] for s in STOPS], xy=np.array([[s[1], s[2]] for s in STOPS]),
            room=[s[4] for s in STOPS], area=[s[5] for s in STOPS])


def _stops(*rows):
    return Stops(stop_id=[r[0] for r in rows], xy=np.array([[r[1], r[2]] for r in rows], dtype=float),
                 room=[r[3] for r in rows], area=[r[4] for r in rows])


def test_area_keys_fall_back_from_labels_to_the_stop():
    assert area_key("r", "a", "s") == "r/a" and area_key("r", None, "s") == "r"
    assert area_key(None, None, "s") == "stop:s"


def test_new_stops_take_their_label_or_the_nearest_old_stops_area():
    problems = Problems()
    got = assign_areas(OLD, _stops(("n0", 9.0, 9.0, "room_a", "east"), ("n1", 4.2, 1.1, None, None)),
                       proximity_m=1.0, allow_new_areas=False, where="new", problems=problems)
    assert not problems
    assert got == {"n0": ("room_a/east", "room_a", "east"), "n1": ("room_b/west", "room_b", "west")}


@pytest.mark.parametrize(("row", "allow", "words"), [
    (("n", 4.2, 1.1, "room_b", "attic"), False, "area 'room_b/attic'"),
    (("n", 4.2, 1.1, "annex", None), False, "room 'annex'"),
    (("n", 3.5, 2.0, None, None), False, "no old stop within update.proximity_m = 1 m"),
])
def test_unknown_labels_and_far_unlabelled_stops_are_problems(row, allow, words):
    problems = Problems()
    assign_areas(OLD, _stops(row), proximity_m=1.0, allow_new_areas=allow, where="new.parquet", problems=problems)
    assert len(problems.items) == 1 and words in str(problems.items[0]) and problems.items[0].fix


def test_a_new_area_is_accepted_when_allowed():
    problems = Problems()
    got = assign_areas(OLD, _stops(("n", 4.2, 1.1, "annex", "north")), proximity_m=1.0, allow_new_areas=True,
                       where="new", problems=problems)
    assert not problems and got["n"][0] == "annex/north"


def geodesic_owner_twin(occ, xy, keys):
    """Brute force: Dijkstra from every stop over free cells (8 moves, no corner cutting), in pure Python;
    returns the owner key of every free cell whose nearest stop is unique (None where two tie)."""
    h, w = occ.grid.shape
    free = occ.grid != OCCUPIED
    best = {}
    for (x, y), key in zip(xy, keys, strict=True):
        start = (int(y / occ.resolution), int(x / occ.resolution))
        dist = {start: 0.0}
        heap = [(0.0, start)]
        while heap:
            d, (r, c) = heapq.heappop(heap)
            if d > dist[(r, c)]:
                continue
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    nr, nc = r + dr, c + dc
                    if (dr, dc) == (0, 0) or not (0 <= nr < h and 0 <= nc < w) or not free[nr, nc]:
                        continue
                    if dr and dc and not (free[r + dr, c] and free[r, c + dc]):
                        continue
                    nd = d + math.hypot(dr, dc)
                    if nd < dist.get((nr, nc), math.inf):
                        dist[(nr, nc)] = nd
                        heapq.heappush(heap, (nd, (nr, nc)))
        for cell, d in dist.items():
            best.setdefault(cell, []).append((d, key))
    out = {}
    for cell, ds in best.items():
        ds.sort()
        out[cell] = ds[0][1] if len(ds) == 1 or ds[1][0] - ds[0][0] > 1e-9 else None
    return out


def test_cells_go_to_the_nearest_stop_along_the_free_space_as_a_brute_force_twin_says():
    occ = floor_map()
    keys = OLD.keys()
    owner, names = cell_owners(occ, OLD.xy, keys)
    twin = geodesic_owner_twin(occ, OLD.xy, keys)
    compared = [(cell, k) for cell, k in twin.items() if k is not None]
    assert len(compared) > 0.9 * (occ.grid != OCCUPIED).sum()
    assert all(names[owner[cell]] == k for cell, k in compared)
    # room_a (x < 2.95 m) keeps its cells but those that see room_b's west stop through the doorway (y 1.5-2.5 m
    # in the wall at x = 3 m); a plain Euclidean partition gives room_b three times as many of them.
    x = np.broadcast_to((np.arange(occ.width) + 0.5) * RES, occ.grid.shape)
    y = np.broadcast_to(((np.arange(occ.height) + 0.5) * RES)[:, None], occ.grid.shape)
    room_a, geodesic = x < 2.95, np.array(names)[owner]
    assert {names[i] for i in np.unique(owner[x < 2.5])} == {"room_a/west", "room_a/east"}
    assert {names[i] for i in np.unique(owner[x > 3.6])} == {"room_b/west", "room_b/east"}
    d = np.stack([np.hypot(x - sx, y - sy) for sx, sy in OLD.xy])
    euclid = np.array(keys)[np.argmin(d, axis=0)]
    assert 3 * (geodesic[room_a] == "room_b/west").sum() <= (euclid[room_a] == "room_b/west").sum()
