"""Road-marking features from one uncalibrated multi-layer LiDAR scan (Kim, Liu & Myung s.2.2).

1. A voxel grid per layer (ring) makes every layer geometrically uniform: one averaged point per
   (ring, voxel), so dense near rings do not dominate.
2. Ground points are kept: a height band about the road surface. The paper finds the traversable area of its
   survey cloud by height differences on an elevation grid; on one scan the road surface is estimated as the
   plane (tilt and height) that holds the most near points (``estimate_ground_plane``), so the band follows the
   body's roll in a turn, its pitch under braking and the road's grade, and a sidewalk one curb above the road
   (its concrete brighter than asphalt along a ring) falls outside it.
3. A ring-based 1D adaptive threshold: along each ring sorted by azimuth, the intensity minus its moving
   average over a window of ``window_m`` metres of arc; a point is a feature when that residual exceeds
   ``offset_sigma`` times the ring's robust spread (median absolute deviation). Each ring is thresholded
   against itself, so the raw intensity never needs calibration.
All steps are vectorised (``np.unique``, ``np.bincount``, ``np.cumsum``, ``np.searchsorted``) but the per-ring sorts
and medians (a loop over the rings: two lexsorts of every point took a third of a scan's extraction).
"""
from __future__ import annotations

import numpy as np


def voxel_filter_per_ring(xyz_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray, voxel_m: float
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average points and intensities per (ring, voxel). Returns (V,3) xyz, (V,) intensity, (V,) ring, the voxels
    in the order of their (ring, x, y, z) cell key.

    The cells are computed one coordinate at a time (a min/max along the first axis of an (N,3) array took 1.1 of a
    scan's 3.8 ms) and each voxel's ring is read back from its key, so ``np.unique`` needs no first index (which
    made it a stable sort): 3.8 -> 1.6 ms for a 44k-point gangnam scan, the same arrays."""
    xyz = np.asarray(xyz_m, dtype=np.float64)
    if len(xyz) == 0:
        return xyz.reshape(0, 3), np.zeros(0), np.zeros(0, dtype=np.int64)
    cells = []
    for d in range(3):
        c = np.floor(xyz[:, d] / voxel_m).astype(np.int64)
        c -= c.min()
        cells.append(c)
    dims = [int(c.max()) + 1 for c in cells]
    r = np.asarray(ring, dtype=np.int64)
    r0 = int(r.min())
    per_ring = dims[0] * dims[1] * dims[2]
    key = ((r - r0) * dims[0] + cells[0]) * dims[1] * dims[2] + cells[1] * dims[2] + cells[2]
    cell_keys, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.column_stack([np.bincount(inverse, weights=xyz[:, d], minlength=len(cell_keys)) for d in range(3)])
    inten = np.bincount(inverse, weights=np.asarray(intensity, dtype=np.float64), minlength=len(cell_keys))
    return sums / counts[:, None], inten / counts, cell_keys // per_ring + r0


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


def _best_slab(pts: np.ndarray, bx: np.ndarray, cy: np.ndarray, window_m: float) -> tuple[float, float, float, int]:
    """Among the tilts (bx, cy), the plane ``z = a + b x + c y`` whose slab ``window_m`` thick holds the most
    points (a histogram of the detilted heights per tilt, windows of two half-bins). Returns (a, b, c, count)."""
    h = pts[None, :, 2] - bx[:, None] * pts[None, :, 0] - cy[:, None] * pts[None, :, 1]  # (T, N)
    half = 0.5 * window_m
    lo = float(h.min())
    nbins = int(np.ceil((float(h.max()) - lo) / half)) + 2
    b = np.floor((h - lo) / half).astype(np.int64)
    counts = np.bincount((np.arange(len(bx))[:, None] * nbins + b).ravel(), minlength=len(bx) * nbins)
    counts = counts.reshape(len(bx), nbins)
    slab = counts[:, :-1] + counts[:, 1:]
    t, k = np.unravel_index(int(np.argmax(slab)), slab.shape)
    return lo + (k + 1) * half, float(bx[t]), float(cy[t]), int(slab[t, k])


def estimate_ground_plane(xyz_m: np.ndarray, near_m: float = 20.0, max_tilt_rad: float = 0.05,
                          tilt_step_rad: float = 0.002, window_m: float = 0.04, max_points: int = 2500
                          ) -> np.ndarray:
    """Road surface of one scan as the plane ``z = a + b x + c y`` (returns ``[a, b, c]``) that holds the most points
    within ``near_m`` (horizontal) of the sensor in a slab ``window_m`` thick: a deterministic search over tilts up
    to ``max_tilt_rad``, coarse (steps of 4 ``tilt_step_rad`` on a fifth of the points) then fine (steps of
    ``tilt_step_rad`` about the coarse best), then two least-squares refits on the points within 0.05 and 0.03 m of
    it. The most populated slab near the sensor is the road the vehicle stands on; a sidewalk, a curb above it,
    holds fewer points. With too few points the plane is level at the heights' mode (``estimate_ground_z``)."""
    xyz = np.asarray(xyz_m, dtype=np.float64)
    near = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) <= near_m]
    z0 = estimate_ground_z(xyz, near_m=min(near_m, 15.0))
    if len(near) < 50 or not np.isfinite(z0):
        return np.array([z0, 0.0, 0.0])
    reach = 1.5 * near_m * max_tilt_rad + 0.5  # heights a tilted road can reach within near_m of the mode
    near = near[np.abs(near[:, 2] - z0) <= reach]
    if len(near) < 50:
        return np.array([z0, 0.0, 0.0])
    if len(near) > max_points:
        near = near[np.linspace(0, len(near) - 1, max_points).astype(np.int64)]
    coarse = 4.0 * tilt_step_rad
    tilts = np.arange(-max_tilt_rad, max_tilt_rad + 0.5 * coarse, coarse)
    bx, cy = (g.ravel() for g in np.meshgrid(tilts, tilts, indexing="ij"))
    _, b0, c0, _ = _best_slab(near[::5], bx, cy, 2.0 * window_m)
    fine = np.arange(-coarse, coarse + 0.5 * tilt_step_rad, tilt_step_rad)
    bx, cy = (g.ravel() for g in np.meshgrid(b0 + fine, c0 + fine, indexing="ij"))
    plane = np.array(_best_slab(near, bx, cy, window_m)[:3])
    A = np.column_stack([np.ones(len(near)), near[:, 0], near[:, 1]])
    for tol in (0.05, 0.03):
        inl = np.abs(near[:, 2] - A @ plane) <= tol
        if inl.sum() < 3:
            break
        plane = np.linalg.lstsq(A[inl], near[inl, 2], rcond=None)[0]
    return plane


def _ring_azimuth_order(ring: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """``np.lexsort((azimuth, ring))``: points by ring, then by azimuth, ties in input order; a stable sort of the
    ring ids, then of each ring's azimuths (0.66 -> ~0.3 ms for 11k points on 17 rings)."""
    by_ring = np.argsort(ring, kind="stable")
    r = ring[by_ring]
    bounds = np.flatnonzero(np.r_[True, r[1:] != r[:-1], True])
    az = azimuth[by_ring]
    for a, b in zip(bounds[:-1], bounds[1:]):
        by_ring[a:b] = by_ring[a:b][np.argsort(az[a:b], kind="stable")]
    return by_ring


def ring_adaptive_threshold(xyz_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray, window_m: float,
                            offset_sigma: float, min_residual: float = 0.0) -> np.ndarray:
    """Boolean mask of points brighter than their ring's local moving average (see the module doc)."""
    n = len(intensity)
    if n == 0:
        return np.zeros(0, dtype=bool)
    xyz = np.asarray(xyz_m, dtype=np.float64)
    ring = np.asarray(ring, dtype=np.int64)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    order = _ring_azimuth_order(ring, azimuth)
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
    abs_residual = np.abs(residual)
    mad = np.array([np.partition(abs_residual[a:a + m], (m - 1) // 2)[(m - 1) // 2] for a, m in zip(starts, sizes)])
    scale = 1.4826 * np.repeat(mad, sizes)
    is_feature = residual > np.maximum(offset_sigma * scale, min_residual)
    mask = np.zeros(n, dtype=bool)
    mask[order] = is_feature & (sizes[ring_of] >= 3)
    return mask


def extract_road_features(xyz_lidar_m: np.ndarray, intensity: np.ndarray, ring: np.ndarray,
                          T_vehicle_lidar: np.ndarray, *, voxel_m: float = 0.1, window_m: float = 3.0,
                          offset_sigma: float = 3.0, ground_band_m: float = 0.15, max_range_m: float = 30.0,
                          ground_z_vehicle_m: float | None = None, ground_model: str = "level") -> np.ndarray:
    """One scan -> (F,2) road-marking feature points in the vehicle frame (x forward, y left).

    ``ground_model``: ``level`` (the heights' mode, a level band), ``plane`` (``estimate_ground_plane``: the band
    about the fitted road plane). ``ground_z_vehicle_m``, when given, is the level road height and wins."""
    xyz = np.asarray(xyz_lidar_m, dtype=np.float64)
    T = np.asarray(T_vehicle_lidar, dtype=np.float64)
    xyz_v = xyz @ T[:3, :3].T + T[:3, 3]
    keep = np.hypot(xyz_v[:, 0], xyz_v[:, 1]) <= max_range_m
    pts, inten, rings = voxel_filter_per_ring(xyz_v[keep], np.asarray(intensity)[keep], np.asarray(ring)[keep],
                                              voxel_m)
    if len(pts) == 0:
        return np.zeros((0, 2))
    if ground_z_vehicle_m is not None:
        surface = np.full(len(pts), float(ground_z_vehicle_m))
    elif ground_model == "plane":
        a, b, c = estimate_ground_plane(pts)
        surface = a + b * pts[:, 0] + c * pts[:, 1]
    elif ground_model == "level":
        surface = np.full(len(pts), estimate_ground_z(pts))
    else:
        raise ValueError(f"ground_model must be 'level' or 'plane', got {ground_model!r}")
    on_ground = np.abs(pts[:, 2] - surface) <= ground_band_m
    pts, inten, rings = pts[on_ground], inten[on_ground], rings[on_ground]
    mask = ring_adaptive_threshold(pts, inten, rings, window_m, offset_sigma)
    return pts[mask, :2]
