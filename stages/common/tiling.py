"""The map's tile grid in the ENU frame, shared by the markings and tiles stages.

Conventions, stated once:
- Tiles are squares of ``size_m`` metres. Tile (i, j) covers east in [i*size, (i+1)*size) and north in
  [j*size, (j+1)*size): half-open, so every point belongs to exactly one tile.
- ``tile_key_of`` is floor(east / size), floor(north / size), corrected so that it always agrees with
  ``tile_bounds`` computed as i*size (float division alone can round a point onto the wrong side of a border).
- Rasters of a tile have ``size_m / cell_m`` rows and columns. Row 0 is the NORTH edge (like an image, row grows
  southwards); column 0 is the WEST edge. Pixel (row, col) covers east in [e0 + col*cell, e0 + (col+1)*cell)
  and north in [n1 - (row+1)*cell, n1 - row*cell), with (e0, n0, e1, n1) the tile bounds.
  The raster's georeference is its lower-left (south-west) corner (e0, n0), which is what
  ``marking_raster.origin_east_m / origin_north_m`` record.
"""
from __future__ import annotations

import numpy as np

from pipeline.errors import ConfigError

DEFAULT_TILE_SIZE_M = 100.0  # the tile edge when neither the tiles params nor the workflow (or map.json) state one


def resolve_tile_size_m(*stated: float | None) -> float:
    """The first stated tile size (a stage param, the workflow's ``tile_size_m`` setting, which a map's identity
    ``map.json`` pins), else ``DEFAULT_TILE_SIZE_M``. A map's published versions state theirs in the manifest
    (``MapReader.tile_size_m``): readers take it from there, never from here."""
    for value in stated:
        if value:
            return float(value)
    return DEFAULT_TILE_SIZE_M


def _check_positive(size_m: float, what: str) -> None:
    if not (np.isfinite(size_m) and size_m > 0):
        raise ConfigError("tile grid", [f"{what} must be a positive finite number of metres, got {size_m!r}"])


def tile_key_of(east_m, north_m, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,) ENU coordinates -> (i, j) int64 arrays of the tiles holding them."""
    _check_positive(size_m, "tile size_m")
    return _floor_index(np.asarray(east_m, float), size_m), _floor_index(np.asarray(north_m, float), size_m)


def _floor_index(x: np.ndarray, size_m: float) -> np.ndarray:
    k = np.floor(x / size_m).astype(np.int64)
    # Rounding in x / size can put a point one tile off; fix it against the bounds k*size exactly.
    k = k - (x < k * size_m)
    k = k + (x >= (k + 1) * size_m)
    return k


def tile_bounds(i, j, size_m: float) -> tuple:
    """Tile key(s) -> (e0, n0, e1, n1) in metres; half-open [e0, e1) x [n0, n1). Works on scalars or arrays."""
    _check_positive(size_m, "tile size_m")
    i = np.asarray(i, np.int64)
    j = np.asarray(j, np.int64)
    e0, n0 = i * size_m, j * size_m
    e1, n1 = (i + 1) * size_m, (j + 1) * size_m
    if e0.ndim == 0:
        return float(e0), float(n0), float(e1), float(n1)
    return e0, n0, e1, n1


def tile_shape_px(size_m: float, cell_m: float) -> tuple[int, int]:
    """(rows, cols) of a tile raster; the tile size must be a whole number of cells."""
    _check_positive(size_m, "tile size_m")
    _check_positive(cell_m, "cell_m")
    n = size_m / cell_m
    n_int = int(round(n))
    if n_int < 1 or abs(n - n_int) > 1e-6 * max(1.0, n):
        raise ConfigError("tile grid", [
            f"tile size {size_m} m is not a whole number of {cell_m} m cells ({n:.6f}); "
            "hint: choose cell_m so that tile_size_m / cell_m is an integer (e.g. 100 m / 0.1 m)"])
    return n_int, n_int


def tile_pixel_of(east_m, north_m, i: int, j: int, size_m: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """ENU points -> (row, col) int64 pixel indices in tile (i, j)'s raster (row 0 = north edge).

    Points inside the tile (``tile_key_of`` == (i, j)) always land in [0, rows) x [0, cols); points outside
    get indices outside that range (useful for halos), following the same cell lattice.
    """
    rows, cols = tile_shape_px(size_m, cell_m)
    east_m = np.asarray(east_m, float)
    north_m = np.asarray(north_m, float)
    e0, n0, _, _ = tile_bounds(i, j, size_m)
    col = np.floor((east_m - e0) / cell_m).astype(np.int64)
    row_from_south = np.floor((north_m - n0) / cell_m).astype(np.int64)
    ki, kj = tile_key_of(east_m, north_m, size_m)
    inside_e = ki == i
    inside_n = kj == j
    col = np.where(inside_e, np.clip(col, 0, cols - 1), col)
    row_from_south = np.where(inside_n, np.clip(row_from_south, 0, rows - 1), row_from_south)
    return rows - 1 - row_from_south, col


def pixel_center_of(row, col, i: int, j: int, size_m: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of tile (i, j)'s raster -> ENU (east, north) of the pixel centre."""
    rows, _ = tile_shape_px(size_m, cell_m)
    e0, n0, _, _ = tile_bounds(i, j, size_m)
    east = e0 + (np.asarray(col, float) + 0.5) * cell_m
    north = n0 + (rows - 1 - np.asarray(row, float) + 0.5) * cell_m
    return east, north


def tiles_touching(east_m, north_m, buffer_m: float, size_m: float) -> list[tuple[int, int]]:
    """Sorted unique tile keys within ``buffer_m`` (a square buffer) of any of the points."""
    east_m = np.asarray(east_m, float)
    north_m = np.asarray(north_m, float)
    if east_m.size == 0:
        return []
    i0, j0 = tile_key_of(east_m - buffer_m, north_m - buffer_m, size_m)
    i1, j1 = tile_key_of(east_m + buffer_m, north_m + buffer_m, size_m)
    keys = set()
    for di in range(int((i1 - i0).max()) + 1):
        for dj in range(int((j1 - j0).max()) + 1):
            ii, jj = i0 + di, j0 + dj
            ok = (ii <= i1) & (jj <= j1)
            keys.update(zip(ii[ok].tolist(), jj[ok].tolist()))
    return sorted(keys)
