"""Layer selection and per-ring ordering (Im et al. 2016 s.2.2: the upper layers, processed one ring at a time).

Motion distortion is ignored: a scan is taken while the vehicle moves (up to ~1.5 m at 15 m/s and 10 Hz) and is
treated as if taken from one pose. Deskewing belongs upstream (pose graph / ingest).
"""
from __future__ import annotations

import numpy as np


def _ring_index(ring: np.ndarray) -> np.ndarray:
    ring = np.asarray(ring)
    if ring.size and int(ring.min()) < 0:
        raise ValueError(f"ring indices must be >= 0 (0 = lowest beam); got minimum {int(ring.min())}")
    return ring.astype(np.intp, copy=False)


ELEVATION_SAMPLE_POINTS = 400_000  # points a ring elevation estimate uses at most (drawn at random, seed 0)
MIN_RING_SAMPLE_POINTS = 50  # a ring with fewer sampled points beyond min_range_m is estimated from all of its points


def _robust_tan_elevation(tan_el: np.ndarray, ring: np.ndarray, size: int) -> np.ndarray:
    """Per ring id (0..size-1): two-pass mean of tan(elevation) (all points, then those within 1 deg of the first
    mean; NaN for a ring without points), and each ring's number of points."""
    count = np.bincount(ring, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        first = np.bincount(ring, tan_el, minlength=size) / count
        near = np.abs(tan_el - first[ring]) < np.tan(np.radians(1.0))
        count2 = np.bincount(ring[near], minlength=size)
        second = np.bincount(ring[near], tan_el[near], minlength=size) / count2
    return np.where(count2 > 0, second, first), count


def estimate_ring_elevation_deg(points_xyz: np.ndarray, ring: np.ndarray, *, min_range_m: float,
                                max_points: int = ELEVATION_SAMPLE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Per ring: its elevation atan2(z, hypot(x, y)) [deg] in the sensor frame, a robust mean of its points.

    A beam's elevation is a constant of the sensor, so a two-pass mean (all points, then those within 1 deg of
    the first mean) is as good as a median here and is computed with bincount (no sort). Above ``max_points``
    points (a 100-scan chunk holds ~5 M) the means use ``max_points`` drawn at random (seed 0: the same points
    every run; a stride could alias with the rings' firing order and miss rings), and a ring with fewer than
    ``MIN_RING_SAMPLE_POINTS`` sampled points beyond ``min_range_m`` is estimated from all of its points.
    Measured on 15 of demo seed 1's scans_raw files (1-2 M points): 0.03-0.21 s -> 0.015 s a file, elevations
    within 3e-8 deg of all points' (the simulator's beams are exact), the same rings.
    Returns (ring ids present, elevation_deg); rings with no point beyond ``min_range_m`` get NaN.
    """
    pts = np.asarray(points_xyz)
    r = _ring_index(ring)
    size = int(r.max()) + 1 if r.size else 0
    ids = np.flatnonzero(np.bincount(r, minlength=size))
    sample = None
    if max_points and len(r) > max_points:
        sample = np.sort(np.random.default_rng(0).integers(0, len(r), max_points))
    tan_el, count = _tan_elevation(pts, r, size, min_range_m, sample)
    if sample is not None:
        few = ids[count[ids] < MIN_RING_SAMPLE_POINTS]
        if few.size:
            lut = np.zeros(size, bool)
            lut[few] = True
            rows = np.flatnonzero(lut[r])
            full, _ = _tan_elevation(pts, r, size, min_range_m, rows)
            tan_el[few] = full[few]
    return ids, np.degrees(np.arctan(tan_el[ids]))


def _tan_elevation(pts: np.ndarray, r: np.ndarray, size: int, min_range_m: float, rows: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``_robust_tan_elevation`` of the points ``rows`` (None: all) beyond ``min_range_m`` horizontally."""
    if rows is not None:
        pts, r = pts[rows], r[rows]
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    horiz = np.sqrt(x * x + y * y)
    keep = horiz > min_range_m
    return _robust_tan_elevation(z[keep] / horiz[keep], r[keep], size)  # tan(elevation): no per-point arctan


def select_layers(points_xyz: np.ndarray, ring: np.ndarray, *, mode: str, n_upper_layers: int,
                  min_elevation_deg: float, min_range_m: float) -> np.ndarray:
    """Ring ids of the upper layers, highest first.

    ``mode="top_n"``: the ``n_upper_layers`` highest ring indices (ring 0 = lowest beam).
    ``mode="elevation"``: rings whose median elevation >= ``min_elevation_deg``, at most ``n_upper_layers`` of
    the highest.
    """
    if mode == "top_n":
        r = _ring_index(ring)
        return np.flatnonzero(np.bincount(r))[::-1][:n_upper_layers]
    if mode != "elevation":
        raise ValueError(f"layer selection mode must be 'elevation' or 'top_n'; got {mode!r}")
    ids, elev_deg = estimate_ring_elevation_deg(points_xyz, ring, min_range_m=min_range_m)
    ok = np.isfinite(elev_deg) & (elev_deg >= min_elevation_deg)
    ids, elev_deg = ids[ok], elev_deg[ok]
    return ids[np.argsort(-elev_deg, kind="stable")][:n_upper_layers]


def order_rings_by_azimuth(xy_m: np.ndarray, layer: np.ndarray, azimuth_rad: np.ndarray | None = None
                           ) -> np.ndarray:
    """Index order grouping points by layer, then by azimuth (counter-clockwise) within each layer.

    Each ring starts just after its widest azimuth gap, so a wall behind the sensor (azimuth +-pi) is not cut.
    """
    az = np.arctan2(xy_m[:, 1], xy_m[:, 0]) if azimuth_rad is None else azimuth_rad
    lay = _ring_index(layer)
    order = np.argsort(lay * 8.0 + (az + np.pi))  # 8 > 2 pi separates layers
    n = order.size
    if n == 0:
        return order
    lay_sorted = lay[order]
    az_sorted = az[order]
    starts = np.flatnonzero(np.r_[True, lay_sorted[1:] != lay_sorted[:-1]])
    stops = np.r_[starts[1:], n]
    counts = stops - starts
    # gap before each point within its ring; the first point's gap wraps from the ring's last point
    gap = np.empty(n)
    gap[1:] = az_sorted[1:] - az_sorted[:-1]
    gap[starts] = az_sorted[starts] - az_sorted[stops - 1] + 2.0 * np.pi
    ring_start = np.repeat(starts, counts)
    ring_max = np.repeat(np.maximum.reduceat(gap, starts), counts)
    at_max = np.flatnonzero(gap == ring_max)
    first = np.r_[True, ring_start[at_max][1:] != ring_start[at_max][:-1]]
    shift = at_max[first] - starts
    local = np.arange(n) - ring_start
    rolled = ring_start + (local + np.repeat(shift, counts)) % np.repeat(counts, counts)
    return order[rolled]


def find_run_starts(xy_m: np.ndarray, layer: np.ndarray, *, break_incidence_deg: float, range_sigma_m: float,
                    max_azimuth_gap_deg: float, azimuth_rad: np.ndarray | None = None) -> np.ndarray:
    """Indices where a new run of contiguous surface starts (points already in ring/azimuth order).

    A run breaks at a layer change, at an azimuth gap > ``max_azimuth_gap_deg``, and where consecutive points are
    farther apart than the adaptive breakpoint distance r sin(dphi) / sin(lambda - dphi) + 3 sigma_r
    (Borges & Aldon 2004), i.e. a surface seen at an incidence below lambda or a range discontinuity.
    """
    n = xy_m.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    x, y = xy_m[:, 0], xy_m[:, 1]
    r = np.sqrt(x * x + y * y)
    az = np.arctan2(y, x) if azimuth_rad is None else azimuth_rad
    dphi = np.abs(az[1:] - az[:-1])
    dphi = np.minimum(dphi, 2.0 * np.pi - dphi)
    lam = np.radians(break_incidence_deg)
    max_gap = np.radians(max_azimuth_gap_deg)
    dphi_c = np.minimum(dphi, 0.5 * lam)
    # sin(dphi) / sin(lam - dphi) = 1 / (sin(lam) cot(dphi) - cos(lam)); dphi is small, so tan is cheap and exact
    ratio = np.tan(dphi_c) / (np.sin(lam) - np.cos(lam) * np.tan(dphi_c))
    d_max = np.minimum(r[:-1], r[1:]) * ratio + 3.0 * range_sigma_m
    dx, dy = x[1:] - x[:-1], y[1:] - y[:-1]
    layer = np.asarray(layer)
    brk = (layer[1:] != layer[:-1]) | (dphi > max_gap) | (dx * dx + dy * dy > d_max * d_max)
    return np.r_[0, np.flatnonzero(brk) + 1].astype(np.int64)
