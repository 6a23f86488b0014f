"""Traversable cells of an elevation grid (Kim et al. 2.1): small height differences to the surrounding cells.

A cell is traversable when it has points and
1. its minimum height differs from every occupied 8-neighbour's minimum by at most ``max_step_m``
   (curb edges, walls and car sides fail),
2. its own min-to-max spread is at most ``max_spread_m`` (walls, poles, car sides, vegetation fail),
3. it lies at most ``max_above_ground_m`` above the ground surface, the grey-scale opening of the minimum
   heights with a ``ground_window_px`` square (flat car roofs are smooth but stand above the opened ground;
   an opening keeps planar slopes exactly, so a sloped road stays at zero height above ground).
Pure array functions (scipy.ndimage); empty cells are NaN in the height arrays.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage


def neighbour_step_m(min_up_m: np.ndarray) -> np.ndarray:
    """Largest |h - h_neighbour| over the occupied 8-neighbours of each cell (0 when none; NaN when empty)."""
    valid = np.isfinite(min_up_m)
    footprint = np.ones((3, 3), bool)
    hi = ndimage.maximum_filter(np.where(valid, min_up_m, -np.inf), footprint=footprint, mode="constant",
                                cval=-np.inf)
    lo = ndimage.minimum_filter(np.where(valid, min_up_m, np.inf), footprint=footprint, mode="constant",
                                cval=np.inf)
    with np.errstate(invalid="ignore"):
        step = np.maximum(hi - min_up_m, min_up_m - lo)
    return np.where(valid, step, np.nan)


def open_ground_m(min_up_m: np.ndarray, window_px: int) -> np.ndarray:
    """Grey-scale opening (erosion then dilation, square ``window_px``) of the minimum-height surface.

    Empty cells do not take part (treated as +inf for the erosion, -inf for the dilation). NaN where the
    opened surface is undefined (no occupied cell in reach).
    """
    window_px = max(1, int(window_px))
    valid = np.isfinite(min_up_m)
    eroded = ndimage.minimum_filter(np.where(valid, min_up_m, np.inf), size=window_px, mode="nearest")
    opened = ndimage.maximum_filter(np.where(np.isfinite(eroded), eroded, -np.inf), size=window_px,
                                    mode="nearest")
    return np.where(np.isfinite(opened), opened, np.nan)


def find_traversable(min_up_m: np.ndarray, max_up_m: np.ndarray, count: np.ndarray, *, max_step_m: float,
                     max_spread_m: float, ground_window_px: int, max_above_ground_m: float,
                     min_points: int = 1) -> np.ndarray:
    """Boolean (rows, cols) mask of traversable cells; see the module docstring."""
    occupied = (np.asarray(count) >= min_points) & np.isfinite(min_up_m)
    h = np.where(occupied, min_up_m, np.nan)
    step = neighbour_step_m(h)
    ground = open_ground_m(h, ground_window_px)
    with np.errstate(invalid="ignore"):
        spread = max_up_m - min_up_m
        ok = (occupied & (step <= max_step_m) & (spread <= max_spread_m)
              & (h - ground <= max_above_ground_m))
    return ok
