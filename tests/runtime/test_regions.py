"""Particles spread over labelled parts of the free space (seeding from an area prior)."""

import numpy as np
import pytest

from pipeline.io.map_yaml import FREE, OCCUPIED, OccupancyMap
from pipeline.runtime.grid import LaserMap


def _map():
    grid = np.full((30, 60), FREE, dtype=np.int8)
    grid[:, :2] = grid[:, -2:] = OCCUPIED
    return LaserMap.from_occupancy(OccupancyMap(grid=grid, resolution=0.1, origin_x=-1.0, origin_y=2.0))


def _regions(lmap):
    _, col = np.divmod(lmap.free_cells, lmap.width)
    return np.select([col < 20, col < 40], [0, 1], -1)  # region 2 gets no cell, the right third none


def test_particles_land_in_their_regions_in_proportion():
    lmap = _map()
    regions = _regions(lmap)
    rng = np.random.default_rng(0)
    poses = lmap.sample_regions(regions, np.array([0.75, 0.25, 0.0]), 20000, rng)
    assert lmap.is_free(poses[:, 0], poses[:, 1]).all()
    row, col = lmap.cells(poses[:, 0], poses[:, 1])
    flat = row * lmap.width + col
    got = regions[np.searchsorted(lmap.free_cells, flat)]
    assert set(np.unique(got)) == {0, 1}
    assert np.mean(got == 0) == pytest.approx(0.75, abs=0.01)
    # uniform within a region: its cells' columns are evenly used, and headings cover the circle
    cols0 = col[got == 0]
    assert np.histogram(cols0, bins=np.arange(2, 21))[0].std() / np.mean(np.histogram(cols0, np.arange(2, 21))[0]) \
        < 0.1
    assert poses[:, 2].min() < -3.0 and poses[:, 2].max() > 3.0


def test_a_region_without_cells_or_weight_gets_nothing():
    lmap = _map()
    regions = _regions(lmap)
    rng = np.random.default_rng(1)
    with pytest.raises(ValueError, match="positive weight"):
        lmap.sample_regions(regions, np.array([0.0, 0.0, 1.0]), 10, rng)
    with pytest.raises(ValueError, match="free cells"):
        lmap.sample_regions(regions[:-1], np.array([1.0]), 10, rng)


def test_filter_starts_over_the_regions():
    from pipeline.config import FilterConfig
    from pipeline.runtime.amcl import AdaptiveMCL, FilterState

    lmap = _map()
    f = AdaptiveMCL(lmap, FilterConfig(max_particles=500, seed=3), range_max=10.0)
    f.init_regions(_regions(lmap), [0.0, 1.0])
    assert len(f.particles) == 500 and f.state == FilterState.RELOCALISING
    _, col = lmap.cells(f.particles[:, 0], f.particles[:, 1])
    assert np.all((col >= 20) & (col < 40))
    np.testing.assert_allclose(f.weights.sum(), 1.0)


def test_injecting_regions_adds_particles_there_and_keeps_weights_normalised():
    from pipeline.config import FilterConfig
    from pipeline.runtime.amcl import AdaptiveMCL, FilterState

    lmap = _map()
    f = AdaptiveMCL(lmap, FilterConfig(max_particles=600, inject_particles=200, seed=4), range_max=10.0)
    f.init_regions(_regions(lmap), [1.0, 0.0])
    f.state = FilterState.LOST
    assert f.inject_regions(_regions(lmap), [0.0, 1.0]) == 200
    assert len(f.particles) == 600 and f.state == FilterState.RELOCALISING
    _, col = lmap.cells(f.particles[:, 0], f.particles[:, 1])
    assert np.sum((col >= 20) & (col < 40)) == 200  # the new ones, in region 1; 200 old ones made room
    np.testing.assert_allclose(f.weights.sum(), 1.0)
