"""One tile's marking layer from its elevation grid: traversable cells -> intensity image -> marking mask.

Pure: an ``ElevationGrid`` (the tile plus a halo) in, cropped arrays out. The halo makes the neighbour test,
the ground opening and the adaptive threshold see across the tile border, so adjacent tiles agree.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.marking_raster.elevation_grid import ElevationGrid
from stages.common.marking_raster.threshold import extract_markings, metres_to_odd_px, metres_to_px, normalise_intensity
from stages.common.marking_raster.traversable import find_traversable


@dataclass(frozen=True)
class MarkingLayer:
    """Result for one tile (all arrays (rows, cols), row 0 = north)."""

    grid: ElevationGrid  # cropped to the tile
    traversable: np.ndarray  # bool
    marking: np.ndarray  # bool
    intensity_u8: np.ndarray  # the normalised image that was thresholded (0 outside traversable)
    intensity_low: float  # raw intensity mapped to level 0
    intensity_high: float  # raw intensity mapped to level 255
    offset_levels: float  # threshold offset used, 8-bit levels


def halo_px_for(cell_m: float, threshold_block_m: float, ground_window_m: float) -> int:
    """Cells of context needed around a tile so its result does not depend on the tile border."""
    block_px = metres_to_odd_px(threshold_block_m, cell_m)
    window_px = metres_to_px(ground_window_m, cell_m)
    return max(block_px // 2, window_px) + 2


def rasterize_grid(grid: ElevationGrid, halo_px: int, *, min_points: int, max_step_m: float,
                   max_spread_m: float, ground_window_m: float, max_above_ground_m: float,
                   threshold_block_m: float, threshold_offset_sigma: float, threshold_min_offset_levels: float,
                   intensity_low_pct: float, intensity_high_pct: float, open_m: float, close_m: float,
                   min_marking_area_m2: float, min_region_m2: float) -> MarkingLayer:
    """Traversable and marking masks of ``grid`` with ``halo_px`` cells of context cropped off each side."""
    cell_m = grid.cell_m
    traversable = find_traversable(grid.min_up_m, grid.max_up_m, grid.count, max_step_m=max_step_m,
                                   max_spread_m=max_spread_m,
                                   ground_window_px=max(3, metres_to_px(ground_window_m, cell_m)),
                                   max_above_ground_m=max_above_ground_m, min_points=min_points)
    image, lo, hi = normalise_intensity(grid.mean_intensity, traversable, intensity_low_pct, intensity_high_pct)
    marking, offset = extract_markings(
        image, traversable, block_px=metres_to_odd_px(threshold_block_m, cell_m),
        offset_sigma=threshold_offset_sigma, min_offset_levels=threshold_min_offset_levels,
        open_px=metres_to_px(open_m, cell_m), close_px=metres_to_px(close_m, cell_m),
        min_area_px=int(np.ceil(min_marking_area_m2 / cell_m**2)),
        min_region_px=int(np.ceil(min_region_m2 / cell_m**2)))
    rows, cols = grid.shape[0] - 2 * halo_px, grid.shape[1] - 2 * halo_px
    sl = (slice(halo_px, halo_px + rows), slice(halo_px, halo_px + cols))
    return MarkingLayer(grid=grid.crop(halo_px, halo_px, rows, cols), traversable=traversable[sl],
                        marking=marking[sl], intensity_u8=image[sl], intensity_low=lo, intensity_high=hi,
                        offset_levels=offset)
