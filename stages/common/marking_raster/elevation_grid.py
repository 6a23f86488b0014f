"""Elevation grid (Kim et al. 2.1, after [3]): per cell min / max / mean height, point count, mean intensity.

Pure numpy: points in, arrays out. Raster convention of stages/common/tiling.py: row 0 is the NORTH edge,
column 0 the WEST edge; the grid's georeference is its south-west corner (origin_east_m, origin_north_m).
Points can be added in pieces (``GridAccumulator``) so a tile is built from a stream with bounded memory.

Lowest consistent surface (``surface_band_m`` > 0): only the points within ``surface_band_m`` of the lowest
height seen in a cell count; points higher up (a car standing or driving over the road in some scans, a person,
an overhanging branch) are dropped before any statistic. When a piece brings a lower surface than the cell
had (road seen after the car moved on), the cell's earlier statistics are discarded and restart from the new
layer (whenever one of its kept points would stand more than the band above the new lowest height). So a
cell occupied by a vehicle in one scan and by road in another ends up as road with the road's intensity,
whatever the order of the scans; the kept points always lie within [lowest, lowest + band]. A restart also
drops earlier points that the new band would still hold (the pieces are whole scans or scan chunks, so the
cell keeps the points of the pieces since its surface was last lowered). A single low outlier point restarts
a cell too (no robust minimum).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ElevationGrid:
    """Per-cell statistics, all (rows, cols). Empty cells: count 0 and NaN elsewhere."""

    min_up_m: np.ndarray
    max_up_m: np.ndarray
    mean_up_m: np.ndarray
    count: np.ndarray  # int64
    mean_intensity: np.ndarray  # float64, raw units
    origin_east_m: float
    origin_north_m: float
    cell_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.count.shape

    def crop(self, row0: int, col0: int, rows: int, cols: int) -> "ElevationGrid":
        """Sub-grid starting at (row0, col0) (row 0 = north), with its own south-west origin."""
        sl = (slice(row0, row0 + rows), slice(col0, col0 + cols))
        below = self.shape[0] - (row0 + rows)  # rows south of the crop
        return ElevationGrid(self.min_up_m[sl], self.max_up_m[sl], self.mean_up_m[sl], self.count[sl],
                             self.mean_intensity[sl], self.origin_east_m + col0 * self.cell_m,
                             self.origin_north_m + below * self.cell_m, self.cell_m)


def cell_index_of(east_m: np.ndarray, north_m: np.ndarray, origin_east_m: float, origin_north_m: float,
                  cell_m: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points -> (row, col, inside) with row 0 = north; ``inside`` marks points that fall in the grid."""
    rows, cols = shape
    col = np.floor((east_m - origin_east_m) / cell_m).astype(np.int64)
    row = rows - 1 - np.floor((north_m - origin_north_m) / cell_m).astype(np.int64)
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    return row, col, inside


class GridAccumulator:
    """Running sums / minima / maxima on flat cell indices; ``add`` pieces, then ``finish``."""

    def __init__(self, origin_east_m: float, origin_north_m: float, cell_m: float, shape: tuple[int, int],
                 surface_band_m: float = 0.0):
        self.surface_band_m = float(surface_band_m)
        self.origin_east_m, self.origin_north_m, self.cell_m = float(origin_east_m), float(origin_north_m), cell_m
        self.shape = (int(shape[0]), int(shape[1]))
        n = self.shape[0] * self.shape[1]
        self._count = np.zeros(n, np.int64)
        self._sum_up = np.zeros(n)
        self._sum_intensity = np.zeros(n)
        self._min_up = np.full(n, np.inf)
        self._max_up = np.full(n, -np.inf)
        self.n_points = 0
        self.n_above_surface = 0  # points dropped as standing above the lowest surface (incl. restarted cells)

    def add(self, points_enu_m: np.ndarray, intensity: np.ndarray) -> int:
        """Add (N,3) east/north/up points with (N,) intensity; returns how many were kept (inside the grid and, with
        a surface band, on the lowest surface)."""
        pts = np.asarray(points_enu_m, float).reshape(-1, 3)
        inten = np.asarray(intensity, float).reshape(-1)
        finite = np.isfinite(pts).all(axis=1) & np.isfinite(inten)
        row, col, inside = cell_index_of(pts[:, 0], pts[:, 1], self.origin_east_m, self.origin_north_m,
                                         self.cell_m, self.shape)
        keep = inside & finite
        flat = row[keep] * self.shape[1] + col[keep]
        up = pts[keep, 2]
        inten = inten[keep]
        n = self._count.size
        if self.surface_band_m > 0:
            flat, up, inten = self._keep_lowest_layer(flat, up, inten)
        self._count += np.bincount(flat, minlength=n)
        self._sum_up += np.bincount(flat, weights=up, minlength=n)
        self._sum_intensity += np.bincount(flat, weights=inten, minlength=n)
        np.minimum.at(self._min_up, flat, up)
        np.maximum.at(self._max_up, flat, up)
        self.n_points += int(flat.size)
        return int(flat.size)

    def _keep_lowest_layer(self, flat: np.ndarray, up: np.ndarray, inten: np.ndarray):
        """Restart cells whose surface dropped below a kept point's band; keep the piece's points within the band.
        Whole-grid arrays (no sort of the piece's cell ids): a few grid-sized temporaries per piece."""
        band = self.surface_band_m
        new_min = self._min_up.copy()
        np.minimum.at(new_min, flat, up)
        # a kept point would now stand above the band: the cell restarts from the new, lower surface
        restart = np.flatnonzero((self._max_up > new_min + band) & (self._count > 0))
        dropped = int(self._count[restart].sum())
        self.n_above_surface += dropped
        self.n_points -= dropped
        self._count[restart] = 0
        self._sum_up[restart] = 0.0
        self._sum_intensity[restart] = 0.0
        self._max_up[restart] = -np.inf
        self._min_up = new_min
        low = up <= new_min[flat] + band
        self.n_above_surface += int(low.size - np.count_nonzero(low))
        return flat[low], up[low], inten[low]

    def finish(self, min_points: int = 1) -> ElevationGrid:
        """Cells with fewer than ``min_points`` points are reported empty (count kept, heights NaN)."""
        ok = self._count >= max(1, min_points)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_up = np.where(ok, self._sum_up / np.maximum(self._count, 1), np.nan)
            mean_int = np.where(ok, self._sum_intensity / np.maximum(self._count, 1), np.nan)
        shape = self.shape
        return ElevationGrid(
            min_up_m=np.where(ok, self._min_up, np.nan).reshape(shape),
            max_up_m=np.where(ok, self._max_up, np.nan).reshape(shape),
            mean_up_m=mean_up.reshape(shape), count=self._count.reshape(shape).copy(),
            mean_intensity=mean_int.reshape(shape), origin_east_m=self.origin_east_m,
            origin_north_m=self.origin_north_m, cell_m=self.cell_m)


def grid_points(points_enu_m: np.ndarray, intensity: np.ndarray, origin_east_m: float, origin_north_m: float,
                cell_m: float, shape: tuple[int, int], min_points: int = 1,
                surface_band_m: float = 0.0) -> ElevationGrid:
    """One-shot elevation grid of (N,3) ENU points; see ``GridAccumulator``."""
    acc = GridAccumulator(origin_east_m, origin_north_m, cell_m, shape, surface_band_m)
    acc.add(points_enu_m, intensity)
    return acc.finish(min_points)
