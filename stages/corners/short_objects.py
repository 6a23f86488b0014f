"""Short-object check: drop corners of objects that a higher layer passes over (trucks, buses, kiosks).

A building corner continues upwards: every higher layer that reaches the corner's range at a modest height
above the sensor sees the wall there (or something in front of it). A vehicle's box corner is seen by the lowest
upper layers only, and the next beam up flies over it and returns from far behind (or not at all). This check
works on one scan; it complements the multi-scan consistency of the corner-map stage.
"""
from __future__ import annotations

import numpy as np

_TWO_PI = 2.0 * np.pi


def estimate_layer_elevation_rad(range_m: np.ndarray, z_m: np.ndarray, layer: np.ndarray, layer_ids: np.ndarray
                                 ) -> np.ndarray:
    """Mean elevation of each layer's points (horizontal range and height of the selected points)."""
    rank = np.zeros(int(layer_ids.max()) + 1 if layer_ids.size else 0, np.intp)
    rank[layer_ids] = np.arange(layer_ids.size)
    dense = rank[layer]
    tan_el = np.bincount(dense, z_m / np.maximum(range_m, 1e-6), minlength=layer_ids.size)
    count = np.bincount(dense, minlength=layer_ids.size)
    return np.arctan(tan_el / np.maximum(count, 1))


def find_passed_over(corner_xy_m: np.ndarray, top_elevation_rad: np.ndarray, xy_m: np.ndarray,
                     azimuth_rad: np.ndarray, layer: np.ndarray, layer_ids: np.ndarray, layer_elevation_rad: np.ndarray,
                     *, max_height_m: float, range_tolerance_m: float = 1.0, window_points: int = 3,
                     max_azimuth_offset_rad: float = np.radians(0.5)) -> np.ndarray:
    """Per corner: True when a layer above its highest supporting layer, passing at most ``max_height_m`` above
    the sensor at the corner's range, has no return within ``range_tolerance_m`` beyond the corner (or nearer)
    within ``max_azimuth_offset_rad`` of the corner's azimuth.

    ``xy_m``, ``azimuth_rad``, ``layer``: the selected points grouped by layer and ordered by azimuth within each
    (layers.order_rings_by_azimuth); ``layer_ids`` sorted ascending with ``layer_elevation_rad`` alike.
    """
    k = corner_xy_m.shape[0]
    out = np.zeros(k, bool)
    if k == 0 or xy_m.shape[0] == 0 or max_height_m <= 0:
        return out
    n = xy_m.shape[0]
    starts = np.flatnonzero(np.r_[True, layer[1:] != layer[:-1]])
    stops = np.r_[starts[1:], n]
    block_layer = layer[starts]
    block_rank = np.repeat(np.arange(starts.size), stops - starts)
    unwrapped = (azimuth_rad - azimuth_rad[starts][block_rank]) % _TWO_PI
    key = block_rank * 8.0 + unwrapped  # non-decreasing over the whole ordered array
    r_pts = np.hypot(xy_m[:, 0], xy_m[:, 1])
    r_c = np.hypot(corner_xy_m[:, 0], corner_xy_m[:, 1])
    az_c = np.arctan2(corner_xy_m[:, 1], corner_xy_m[:, 0])
    block_elev = layer_elevation_rad[np.searchsorted(layer_ids, block_layer)]
    ci, bi = np.meshgrid(np.arange(k), np.arange(starts.size), indexing="ij")
    ci, bi = ci.ravel(), bi.ravel()
    pair = (block_elev[bi] > top_elevation_rad[ci] + 1e-4) & (r_c[ci] * np.tan(block_elev[bi]) <= max_height_m)
    ci, bi = ci[pair], bi[pair]
    if ci.size == 0:
        return out
    q = bi * 8.0 + (az_c[ci] - azimuth_rad[starts[bi]]) % _TWO_PI
    pos = np.searchsorted(key, q)
    win = pos[:, None] + np.arange(-window_points, window_points)[None, :]
    inside = (win >= starts[bi][:, None]) & (win < stops[bi][:, None])
    win = np.clip(win, 0, n - 1)
    d_az = np.abs((azimuth_rad[win] - az_c[ci][:, None] + np.pi) % _TWO_PI - np.pi)
    sees = inside & (d_az <= max_azimuth_offset_rad) & (r_pts[win] < r_c[ci][:, None] + range_tolerance_m)
    np.logical_or.at(out, ci, ~sees.any(axis=1))
    return out
