"""Road-feature building blocks against plain references: the per-ring voxel means against a dictionary grouping,
the per-ring azimuth order against ``np.lexsort``, and the adaptive threshold against a point-by-point reference."""
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
    """The module doc's threshold, one ring at a time and one point at a time: the residual against the mean of the
    ring's points within half a window of arc, above offset_sigma times 1.4826 times the ring's (lower) median
    absolute residual; rings of fewer than 3 points have no feature."""
    mask = np.zeros(len(intensity), dtype=bool)
    for r in np.unique(ring):
        idx = np.flatnonzero(ring == r)
        idx = idx[np.argsort(np.arctan2(xyz[idx, 1], xyz[idx, 0]), kind="stable")]
        if len(idx) < 3:
            continue
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xyz[idx, :2], axis=0).T))])
        val = intensity[idx]
        residual = np.array([val[k] - val[np.abs(arc - arc[k]) <= 0.5 * window_m].mean() for k in range(len(idx))])
        mad = np.sort(np.abs(residual))[(len(idx) - 1) // 2]
        mask[idx] = residual > offset_sigma * 1.4826 * mad
    return mask


def _rings(seed: int, n_rings: int = 12, per_ring: int = 500):
    """Ground rings: circles of growing radius, points at jittered azimuths, gamma intensities with bright paint."""
    rng = np.random.default_rng(seed)
    xyz, inten, ring = [], [], []
    for r in range(n_rings):
        az = np.sort(rng.uniform(-np.pi, np.pi, per_ring))
        radius = 4.0 + 1.5 * r + rng.normal(0, 0.02, per_ring)
        xyz.append(np.column_stack([radius * np.cos(az), radius * np.sin(az), np.full(per_ring, -1.9)]))
        value = rng.gamma(4.0, 3.0, per_ring) * (1.0 + 0.3 * r)  # a gain per ring
        value[np.abs(az - 0.5) < 0.05] += 40.0  # a painted stripe
        inten.append(value)
        ring.append(np.full(per_ring, r))
    order = rng.permutation(n_rings * per_ring)
    return np.concatenate(xyz)[order], np.concatenate(inten)[order], np.concatenate(ring)[order]


def test_adaptive_threshold_equals_a_point_by_point_reference():
    for seed in (3, 4, 5):
        xyz, inten, ring = _rings(seed)
        ring[:2] = 30  # a ring of two points: never a feature
        got = ring_adaptive_threshold(xyz, inten, ring, window_m=3.0, offset_sigma=2.0)
        np.testing.assert_array_equal(got, _threshold_reference(xyz, inten, ring, 3.0, 2.0))
        assert got.any() and not got[:2].any()
