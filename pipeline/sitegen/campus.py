"""A large, sparse, laser-only site: buildings around open courtyards, streets and plazas.

The reference office is a dense indoor floor where every beam returns within a few metres. Real robots
also drive campuses: long straight facades, courtyards tens of metres across, plazas where a third of
the beams return nothing within range, scans a metre apart. That is where particle filters diverge
(long featureless walls, few returns, large motion between updates), so this generator makes such a site
reproducibly from a seed: an occupancy map as a laser-built map shows it (facades occupied, building
interiors unknown, open ground free), the world the laser sees (the map plus unmapped parked cars), and
one long drive through streets, courtyard passages and across plazas. docs/reference-site.md shows it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from pipeline.config import OdometryNoise, Strict
from pipeline.io.map_yaml import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from pipeline.sitegen.laser import fill_discs, fill_rects
from pipeline.sitegen.routes import resample, smooth_headings

BLOCK_KINDS = ("building", "courtyard", "plaza")


class CampusLaser(Strict):
    beams: int = Field(361, ge=2)
    fov_deg: float = Field(180.0, gt=0, le=360)
    range_max: float = Field(40.0, gt=1, description="no return beyond this, m (stored as range_max)")
    noise_sigma: float = Field(0.02, ge=0, description="range noise on returns, m")
    dropout: float = Field(0.02, ge=0, le=1, description="share of beams lost to range_max (glass, dark)")


class CampusPreset(Strict):
    """A laser-only site preset (`configs/laser_sites/*.yaml`)."""

    name: str = "campus"
    size: tuple[float, float] = Field((270.0, 240.0), description="site width (x) and height (y), m")
    resolution: float = Field(0.05, gt=0, description="map cell size, m")
    blocks: tuple[int, int] = Field((5, 4), description="block grid between streets (x, y)")
    street_width: float = Field(12.0, gt=4, description="street width between blocks and around them, m")
    kinds: dict[str, float] = Field({"building": 0.45, "courtyard": 0.35, "plaza": 0.2},
                                    description="share of blocks of each kind (building, courtyard, plaza)")
    setback_max: float = Field(3.0, ge=0, description="random setback of a facade from its block edge, m")
    wing_depth: float = Field(10.0, gt=3, description="depth of a courtyard block's building wings, m")
    passage_width: float = Field(6.0, gt=2, description="width of a passage through a wing, m")
    wall_thickness: float = Field(0.3, gt=0)
    street_tree_spacing: float = Field(6.0, gt=2, description="mean spacing of trees along streets, m")
    plaza_trees: int = Field(20, ge=0, description="trees per plaza")
    parked_cars: int = Field(25, ge=0, description="cars along streets, unknown to the map")
    route_length: float = Field(1750.0, gt=10, description="length of the drive, m")
    scan_every_m: float = Field(0.9, gt=0, description="distance between scans, m")
    lateral_jitter: float = Field(1.5, ge=0, description="how far the drive strays from a street's axis, m")
    heading_wobble_deg: float = Field(1.0, ge=0)
    laser: CampusLaser = CampusLaser()
    odometry_noise: OdometryNoise = OdometryNoise(alpha1=0.004, alpha2=0.00008, alpha3=0.0006, alpha4=0.0001)
    seed: int = 0

    @model_validator(mode="after")
    def _fits(self) -> CampusPreset:
        bad = sorted(set(self.kinds) - set(BLOCK_KINDS))
        if bad or not any(v > 0 for v in self.kinds.values()):
            raise ValueError(f"kinds must give positive shares to some of {BLOCK_KINDS}, got {self.kinds}")
        bw, bh = self.block_size
        if min(bw, bh) < 2 * self.wing_depth + 4:
            raise ValueError(f"blocks of {bw:.1f} x {bh:.1f} m cannot hold two {self.wing_depth} m wings and a "
                             "court: enlarge size, or reduce blocks, street_width or wing_depth")
        return self

    @property
    def block_size(self) -> tuple[float, float]:
        (w, h), (nx, ny), s = self.size, self.blocks, self.street_width
        return (w - (nx + 1) * s) / nx, (h - (ny + 1) * s) / ny


@dataclass
class Campus:
    """The generated site: its map, the laser's world, the block kinds and the route graph."""

    map: OccupancyMap
    world: OccupancyMap
    kinds: np.ndarray  # (ny, nx) str
    nodes: np.ndarray  # (N, 2) route graph nodes, m
    edges: dict[int, list[int]]


def _block_origin(p: CampusPreset, i: int, j: int) -> tuple[float, float]:
    bw, bh = p.block_size
    return p.street_width + i * (bw + p.street_width), p.street_width + j * (bh + p.street_width)


def generate_campus(p: CampusPreset) -> Campus:
    """Map, world and route graph of preset `p` (seeded by `p.seed`)."""
    rng = np.random.default_rng(p.seed)
    w, h = p.size
    res = p.resolution
    shape = (int(round(h / res)), int(round(w / res)))
    frame = OccupancyMap(np.zeros(shape, np.int8), res)
    footprint, trees = np.zeros(shape, bool), []
    nx, ny = p.blocks
    bw, bh = p.block_size
    names = [k for k in BLOCK_KINDS if p.kinds.get(k, 0) > 0]
    share = np.array([p.kinds[k] for k in names]) / sum(p.kinds[k] for k in names)
    kinds = rng.choice(names, size=(ny, nx), p=share)
    s = p.street_width
    xs = [s / 2 + i * (bw + s) for i in range(nx + 1)]  # street axes
    ys = [s / 2 + j * (bh + s) for j in range(ny + 1)]
    nodes = [(x, y) for y in ys for x in xs]
    edges: dict[int, set[int]] = {k: set() for k in range(len(nodes))}

    def node(xy) -> int:
        nodes.append(tuple(xy))
        edges[len(nodes) - 1] = set()
        return len(nodes) - 1

    def link(a: int, b: int) -> None:
        edges[a].add(b)
        edges[b].add(a)

    def grid_node(i: int, j: int) -> int:
        return j * (nx + 1) + i

    # Street edges, split at the middle of each block side (where passages and plaza paths join).
    side_mid: dict[tuple, int] = {}
    for j in range(ny + 1):
        for i in range(nx):
            m = node(((xs[i] + xs[i + 1]) / 2, ys[j]))
            link(grid_node(i, j), m), link(m, grid_node(i + 1, j))
            side_mid[("h", i, j)] = m
    for i in range(nx + 1):
        for j in range(ny):
            m = node((xs[i], (ys[j] + ys[j + 1]) / 2))
            link(grid_node(i, j), m), link(m, grid_node(i, j + 1))
            side_mid[("v", i, j)] = m
    for j in range(ny):
        for i in range(nx):
            bx, by = _block_origin(p, i, j)
            cx, cy = bx + bw / 2, by + bh / 2
            sides = {"s": side_mid[("h", i, j)], "n": side_mid[("h", i, j + 1)],
                     "w": side_mid[("v", i, j)], "e": side_mid[("v", i + 1, j)]}
            kind = kinds[j, i]
            if kind == "building":
                sb = rng.uniform(0, p.setback_max, 4)
                x0, y0, x1, y1 = bx + sb[0], by + sb[1], bx + bw - sb[2], by + bh - sb[3]
                fill_rects(footprint, frame, [((x0 + x1) / 2, (y0 + y1) / 2, 0.0, x1 - x0, y1 - y0)])
            elif kind == "courtyard":
                d, half = p.wing_depth, p.passage_width / 2
                wings = {"s": (bx, by, bx + bw, by + d), "n": (bx, by + bh - d, bx + bw, by + bh),
                         "w": (bx, by + d, bx + d, by + bh - d), "e": (bx + bw - d, by + d, bx + bw, by + bh - d)}
                open_sides = set(rng.choice(list(wings), size=int(rng.integers(1, 3)), replace=False))
                centre = node((cx, cy))
                for side, (x0, y0, x1, y1) in wings.items():
                    pieces = [(x0, y0, x1, y1)]
                    if side in open_sides:  # a passage through the wing's middle
                        pieces = ([(x0, y0, cx - half, y1), (cx + half, y0, x1, y1)] if side in "sn"
                                  else [(x0, y0, x1, cy - half), (x0, cy + half, x1, y1)])
                        link(sides[side], centre)
                    for a, b, c, e in pieces:
                        fill_rects(footprint, frame, [((a + c) / 2, (b + e) / 2, 0.0, c - a, e - b)])
                court = (bx + d + 3, by + d + 3, bx + bw - d - 3, by + bh - d - 3)
                trees += _scatter(rng, court, max(1, p.plaza_trees // 3), keep_clear=[(cx, cy)], axes=(cx, cy))
            else:  # a plaza: paths from each side to the centre, trees off the paths
                centre = node((cx, cy))
                for m in sides.values():
                    link(m, centre)
                trees += _scatter(rng, (bx + 2, by + 2, bx + bw - 2, by + bh - 2), p.plaza_trees,
                                  keep_clear=[(cx, cy)], axes=(cx, cy))
    # Trees along the streets, a metre off the kerb; none across a crossing street or a path's entry.
    cross_x = [(x, s / 2) for x in xs] + [(_block_origin(p, i, 0)[0] + bw / 2, 3.0) for i in range(nx)]
    cross_y = [(y, s / 2) for y in ys] + [(_block_origin(p, 0, j)[1] + bh / 2, 3.0) for j in range(ny)]
    for y in ys:
        trees += _row(rng, (0, w), y + rng.choice([-1, 1]) * (s / 2 - 1.2), p.street_tree_spacing, "x", cross_x)
    for x in xs:
        trees += _row(rng, (0, h), x + rng.choice([-1, 1]) * (s / 2 - 1.2), p.street_tree_spacing, "y", cross_y)
    # Facades: the footprints' outer `wall_thickness` (a laser sees the outside of a building, not its rooms).
    from scipy.ndimage import binary_erosion

    walls = footprint & ~binary_erosion(footprint, iterations=max(1, int(round(p.wall_thickness / res))))
    tree_mask = np.zeros(shape, bool)
    fill_discs(tree_mask, frame, trees)
    tree_mask &= ~footprint
    grid = np.full(shape, FREE, np.int8)
    grid[footprint] = UNKNOWN  # nobody scanned inside
    grid[walls | tree_mask] = OCCUPIED
    site_map = OccupancyMap(grid, res)
    world = grid.copy()
    cars = np.zeros(shape, bool)
    fill_rects(cars, frame, _parked_cars(rng, p, xs, ys, cross_x, cross_y))
    world[cars & (grid == FREE)] = OCCUPIED
    return Campus(site_map, OccupancyMap(world, res), kinds, np.asarray(nodes),
                  {k: sorted(v) for k, v in edges.items()})


def _scatter(rng, box, n: int, keep_clear, axes=None) -> list[tuple[float, float, float]]:
    """`n` trees (x, y, r) in `box`, 3 m from `keep_clear` points and (plazas) 2.5 m from the paths `axes`."""
    x0, y0, x1, y1 = box
    out = []
    for _ in range(50 * max(n, 1)):
        if len(out) == n or x1 <= x0 or y1 <= y0:
            break
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        if any(math.hypot(x - a, y - b) < 3 for a, b in keep_clear):
            continue
        if axes is not None and min(abs(x - axes[0]), abs(y - axes[1])) < 2.5:
            continue
        out.append((x, y, float(rng.uniform(0.2, 0.45))))
    return out


def _clear(pos: float, avoid) -> bool:
    return all(abs(pos - c) >= half + 1.0 for c, half in avoid)


def _row(rng, span, offset: float, spacing: float, along: str, avoid) -> list[tuple[float, float, float]]:
    """Trees along a street: gaps drawn around `spacing`, some missing, none within `avoid` (centre, half)."""
    out, pos = [], span[0] + rng.uniform(0, spacing)
    while pos < span[1]:
        if rng.random() < 0.7 and _clear(pos, avoid):
            r = float(rng.uniform(0.15, 0.35))
            out.append((pos, offset, r) if along == "x" else (offset, pos, r))
        pos += spacing * rng.uniform(0.6, 1.4)
    return out


def _parked_cars(rng, p: CampusPreset, xs, ys, cross_x, cross_y) -> list[tuple]:
    """Cars parked along the kerbs (4.5 x 1.8 m), unknown to the map: the world has them, the map does not."""
    out = []
    for _ in range(100 * p.parked_cars):
        if len(out) == p.parked_cars:
            break
        along = float(rng.uniform(0, p.size[0] if len(out) % 2 == 0 else p.size[1]))
        kerb = rng.choice([-1, 1]) * (p.street_width / 2 - 2.5)
        if len(out) % 2 == 0 and _clear(along, [(c, h + 2.25) for c, h in cross_x]):
            out.append((along, float(rng.choice(ys) + kerb), 0.0, 4.5, 1.8))
        elif len(out) % 2 == 1 and _clear(along, [(c, h + 2.25) for c, h in cross_y]):
            out.append((float(rng.choice(xs) + kerb), along, math.pi / 2, 4.5, 1.8))
    return out


def drive(campus: Campus, p: CampusPreset, rng: np.random.Generator) -> np.ndarray:
    """Ground-truth map_from_base poses (N, 3), one per `scan_every_m`: a random walk on the route graph
    (no U-turns unless at a dead end) until `route_length`, each waypoint jittered off the axis."""
    nodes, edges = campus.nodes, campus.edges
    here = int(rng.integers(len(nodes)))
    prev, length, path = -1, 0.0, [nodes[here]]
    while length < p.route_length:
        options = [n for n in edges[here] if n != prev] or list(edges[here])
        nxt = int(rng.choice(options))
        point = nodes[nxt] + rng.uniform(-p.lateral_jitter, p.lateral_jitter, 2)
        length += float(np.hypot(*(point - path[-1])))
        path.append(point)
        prev, here = here, nxt
    xy, direction = resample(np.asarray(path), p.scan_every_m)
    theta = smooth_headings(direction, math.radians(p.heading_wobble_deg), rng)
    return np.column_stack([xy, theta])
