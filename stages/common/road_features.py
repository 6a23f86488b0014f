"""Road-marking features from one uncalibrated multi-layer LiDAR scan (Kim, Liu & Myung s.2.2).

1. A voxel grid per layer (ring) makes every layer geometrically uniform: one averaged point per
   (ring, voxel), so dense near rings do not dominate.
2. Ground points are kept (height band about the ground level, estimated per scan as the mode of the
   heights of near points unless given).
3. A ring-based 1D adaptive threshold: along each ring sorted by azimuth, the intensity minus its moving
   average over a window of ``window_m`` metres of arc; a point is a feature when that residual exceeds
   ``offset_sigma`` times the ring's robust spread (median absolute deviation). Each ring is thresholded
   against itself, so the raw intensity never needs calibration.
All steps are vectorised (``np.unique``, ``np.bincount``, ``np.cumsum``, ``np.searchsorted``).
"""
from __future__ import annotations

import numpy as np


def voxel_filter_per_ring(xyz_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray, voxel_m: float
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average points and intensities per (ring, voxel). Returns (V,3) xyz, (V,) intensity, (V,) ring."""
    xyz = np.asarray(xyz_m, dtype=np.float64)
    if len(xyz) == 0:
        return xyz.reshape(0, 3), np.zeros(0), np.zeros(0, dtype=np.int64)
    cells = np.floor(xyz / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    r = np.asarray(ring, dtype=np.int64)
    key = ((r - r.min()) * dims[0] + cells[:, 0]) * dims[1] * dims[2] + cells[:, 1] * dims[2] + cells[:, 2]
    _, first, inverse, counts = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.column_stack([np.bincount(inverse, weights=xyz[:, d], minlength=len(first)) for d in range(3)])
    inten = np.bincount(inverse, weights=np.asarray(intensity, dtype=np.float64), minlength=len(first))
    return sums / counts[:, None], inten / counts, np.asarray(ring, dtype=np.int64)[first]


def estimate_ground_z(xyz_m: np.ndarray, near_m: float = 15.0, bin_m: float = 0.05) -> float:
    """Ground height as the mode of the heights of points within ``near_m`` (horizontal) of the sensor."""
    xyz = np.asarray(xyz_m, dtype=np.float64)
    z = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) <= near_m, 2]
    if len(z) == 0:
        return float("nan")
    bins = np.floor(z / bin_m).astype(np.int64)
    lo = bins.min()
    counts = np.bincount(bins - lo)
    counts = np.convolve(counts, np.ones(3), mode="same")  # smooth a bin edge that splits the ground
    return float((np.argmax(counts) + lo + 0.5) * bin_m)


def ring_adaptive_threshold(xyz_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray, window_m: float,
                            offset_sigma: float, min_residual: float = 0.0) -> np.ndarray:
    """Boolean mask of points brighter than their ring's local moving average (see the module doc)."""
    n = len(intensity)
    if n == 0:
        return np.zeros(0, dtype=bool)
    xyz = np.asarray(xyz_m, dtype=np.float64)
    ring = np.asarray(ring, dtype=np.int64)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    order = np.lexsort((azimuth, ring))
    r_sorted, xy = ring[order], xyz[order, :2]
    step = np.hypot(*np.diff(xy, axis=0).T)
    new_ring = np.diff(r_sorted) != 0
    step = np.where(new_ring, 10.0 * window_m + 1.0, step)  # a gap wider than any window between rings
    arc = np.concatenate([[0.0], np.cumsum(step)])
    val = np.asarray(intensity, dtype=np.float64)[order]
    csum = np.concatenate([[0.0], np.cumsum(val)])
    lo = np.searchsorted(arc, arc - 0.5 * window_m, side="left")
    hi = np.searchsorted(arc, arc + 0.5 * window_m, side="right")
    residual = val - (csum[hi] - csum[lo]) / (hi - lo)
    # per-ring robust spread: median absolute residual, via a sort within rings
    starts = np.flatnonzero(np.concatenate([[True], new_ring]))
    sizes = np.diff(np.concatenate([starts, [n]]))
    ring_of = np.repeat(np.arange(len(starts)), sizes)
    abs_sorted = np.abs(residual)[np.lexsort((np.abs(residual), ring_of))]
    mad = abs_sorted[starts + (sizes - 1) // 2]
    scale = 1.4826 * np.repeat(mad, sizes)
    is_feature = residual > np.maximum(offset_sigma * scale, min_residual)
    mask = np.zeros(n, dtype=bool)
    mask[order] = is_feature & (sizes[ring_of] >= 3)
    return mask


def extract_road_features(xyz_lidar_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray,
                          T_vehicle_lidar: np.ndarray, *, voxel_m: float = 0.1, window_m: float = 3.0,
                          offset_sigma: float = 3.0, ground_band_m: float = 0.15, max_range_m: float = 30.0,
                          ground_z_vehicle_m: float | None = None) -> np.ndarray:
    """One scan -> (F,2) road-marking feature points in the vehicle frame (x forward, y left)."""
    xyz = np.asarray(xyz_lidar_m, dtype=np.float64)
    T = np.asarray(T_vehicle_lidar, dtype=np.float64)
    xyz_v = xyz @ T[:3, :3].T + T[:3, 3]
    keep = np.hypot(xyz_v[:, 0], xyz_v[:, 1]) <= max_range_m
    pts, inten, rings = voxel_filter_per_ring(xyz_v[keep], np.asarray(intensity)[keep], np.asarray(ring)[keep],
                                              voxel_m)
    if len(pts) == 0:
        return np.zeros((0, 2))
    ground_z = estimate_ground_z(pts) if ground_z_vehicle_m is None else ground_z_vehicle_m
    on_ground = np.abs(pts[:, 2] - ground_z) <= ground_band_m
    pts, inten, rings = pts[on_ground], inten[on_ground], rings[on_ground]
    mask = ring_adaptive_threshold(pts, inten, rings, window_m, offset_sigma)
    return pts[mask, :2]
