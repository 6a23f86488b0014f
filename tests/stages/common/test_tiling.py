"""Tile grid properties: key <-> bounds <-> pixel (hypothesis), raster orientation, bad sizes."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.errors import ConfigError
from stages.common.tiling import pixel_center_of, tile_bounds, tile_key_of, tile_pixel_of, tile_shape_px, tiles_touching

coord = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
grid = st.sampled_from([(100.0, 0.1), (50.0, 0.25), (20.0, 0.1), (64.0, 0.5), (0.3, 0.1)])


@settings(max_examples=300, deadline=None)
@given(east=coord, north=coord, g=grid)
def test_key_bounds_pixel_agree(east, north, g):
    size_m, cell_m = g
    i, j = tile_key_of(np.array([east]), np.array([north]), size_m)
    e0, n0, e1, n1 = tile_bounds(int(i[0]), int(j[0]), size_m)
    assert e0 <= east < e1 and n0 <= north < n1
    rows, cols = tile_shape_px(size_m, cell_m)
    row, col = tile_pixel_of(np.array([east]), np.array([north]), int(i[0]), int(j[0]), size_m, cell_m)
    assert 0 <= row[0] < rows and 0 <= col[0] < cols
    ce, cn = pixel_center_of(row, col, int(i[0]), int(j[0]), size_m, cell_m)
    tol = cell_m / 2 + 1e-9 * max(1.0, abs(east), abs(north))
    assert abs(ce[0] - east) <= tol and abs(cn[0] - north) <= tol


@settings(max_examples=200, deadline=None)
@given(i=st.integers(-10_000, 10_000), j=st.integers(-10_000, 10_000), data=st.data(), g=grid)
def test_pixel_center_round_trip(i, j, data, g):
    size_m, cell_m = g
    rows, cols = tile_shape_px(size_m, cell_m)
    row = data.draw(st.integers(0, rows - 1))
    col = data.draw(st.integers(0, cols - 1))
    ce, cn = pixel_center_of(row, col, i, j, size_m, cell_m)
    ki, kj = tile_key_of(np.array([ce]), np.array([cn]), size_m)
    assert (ki[0], kj[0]) == (i, j)
    r2, c2 = tile_pixel_of(np.array([ce]), np.array([cn]), i, j, size_m, cell_m)
    assert (r2[0], c2[0]) == (row, col)


def test_row_zero_is_north_and_col_zero_is_west():
    row, col = tile_pixel_of(np.array([0.05, 99.95, 0.05]), np.array([99.95, 0.05, 0.05]), 0, 0, 100.0, 0.1)
    assert row.tolist() == [0, 999, 999] and col.tolist() == [0, 999, 0]


def test_half_open_borders_and_negative_keys():
    i, j = tile_key_of(np.array([100.0, -0.0, -1e-9, 99.99999999999999]), np.array([0.0, 0.0, -100.0, 0.0]),
                       100.0)
    assert i.tolist() == [1, 0, -1, 0] and j.tolist() == [0, 0, -1, 0]
    assert tile_bounds(-1, -1, 100.0) == (-100.0, -100.0, 0.0, 0.0)


def test_points_outside_the_tile_follow_the_lattice():
    row, col = tile_pixel_of(np.array([-0.05, 100.05]), np.array([50.0, 50.0]), 0, 0, 100.0, 0.1)
    assert col.tolist() == [-1, 1000] and row.tolist() == [499, 499]


def test_tiles_touching_covers_the_buffer():
    keys = tiles_touching(np.array([5.0, 250.0]), np.array([5.0, 50.0]), 30.0, 100.0)
    assert keys == [(-1, -1), (-1, 0), (0, -1), (0, 0), (2, 0)]
    assert tiles_touching(np.array([]), np.array([]), 30.0, 100.0) == []


@pytest.mark.parametrize("size_m,cell_m", [(100.0, 0.3), (100.0, 0.0), (-5.0, 0.1), (float("nan"), 0.1)])
def test_bad_grid_sizes_raise_config_error(size_m, cell_m):
    with pytest.raises(ConfigError):
        tile_shape_px(size_m, cell_m)
