"""Road-feature building blocks against plain references: the per-ring voxel means against a dictionary grouping,
the per-ring azimuth order against ``np.lexsort``, and the adaptive threshold against its all-points formulation."""
from __future__ import annotations

from collections import defaultdict

import numpy as np

from stages.common.road_features import _ring_azimuth_order, ring_adaptive_threshold, voxel_filter_per_ring


def _scan(seed: int, n: int = 6000):
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(-20, 20, n), rng.uniform(-20, 20, n), rng.normal(-1.9, 0.05, n)])
    ring = rng.integers(3, 19, n)
    inten = rng.gamma(2.0, 5.0, n)
    return xyz, inten, ring


def test_voxel_means_per_ring_equal_a_dictionary_grouping():
    xyz, inten, ring = _scan(1)
    xyz[:50] = xyz[0]  # many points in one voxel of one ring
    ring[:50] = ring[0]
    pts, mean_inten, rings = voxel_filter_per_ring(xyz, inten, ring, 0.5)
    groups = defaultdict(list)
    for k, cell in enumerate(np.floor(xyz / 0.5).astype(np.int64)):
        groups[(int(ring[k]), *cell.tolist())].append(k)
    keys = sorted(groups)
    assert len(pts) == len(keys)
    np.testing.assert_array_equal(rings, [k[0] for k in keys])
    np.testing.assert_allclose(pts, [xyz[groups[k]].mean(axis=0) for k in keys], atol=1e-12)
    np.testing.assert_allclose(mean_inten, [inten[groups[k]].mean() for k in keys], atol=1e-12)


def test_ring_azimuth_order_is_lexsorts_with_its_ties():
    rng = np.random.default_rng(2)
    ring = rng.integers(0, 9, 5000)
    azimuth = np.round(rng.uniform(-np.pi, np.pi, 5000), 2)  # many equal azimuths on one ring
    np.testing.assert_array_equal(_ring_azimuth_order(ring, azimuth), np.lexsort((azimuth, ring)))


def _threshold_reference(xyz, intensity, ring, window_m, offset_sigma):
    """The threshold with two lexsorts of all points (the formulation before the per-ring loops)."""
    n = len(intensity)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    order = np.lexsort((azimuth, ring))
    r_sorted, xy = ring[order], xyz[order, :2]
    step = np.hypot(*np.diff(xy, axis=0).T)
    new_ring = np.diff(r_sorted) != 0
    step = np.where(new_ring, 10.0 * window_m + 1.0, step)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    val = intensity[order]
    csum = np.concatenate([[0.0], np.cumsum(val)])
    lo = np.searchsorted(arc, arc - 0.5 * window_m, side="left")
    hi = np.searchsorted(arc, arc + 0.5 * window_m, side="right")
    residual = val - (csum[hi] - csum[lo]) / (hi - lo)
    starts = np.flatnonzero(np.concatenate([[True], new_ring]))
    sizes = np.diff(np.concatenate([starts, [n]]))
    ring_of = np.repeat(np.arange(len(starts)), sizes)
    abs_sorted = np.abs(residual)[np.lexsort((np.abs(residual), ring_of))]
    scale = 1.4826 * np.repeat(abs_sorted[starts + (sizes - 1) // 2], sizes)
    mask = np.zeros(n, dtype=bool)
    mask[order] = (residual > offset_sigma * scale) & (sizes[ring_of] >= 3)
    return mask


def test_adaptive_threshold_equals_its_all_points_formulation():
    for seed in (3, 4, 5):
        xyz, inten, ring = _scan(seed)
        ring[:2] = 30  # a ring of two points: never a feature
        got = ring_adaptive_threshold(xyz, inten, ring, window_m=3.0, offset_sigma=2.0)
        np.testing.assert_array_equal(got, _threshold_reference(xyz, inten, ring, 3.0, 2.0))
        assert got.any() and not got[:2].any()
