"""Clustering oracles: scattered observations around known corners come back as exactly those corners."""
from __future__ import annotations

import numpy as np
import pytest

from stages.cornermap.clustering import cluster_observations, split_spread_clusters
from stages.cornermap.partition import cluster_partitioned
from tests.stages.cornermap.cornermap_synth import scatter_enu, true_corners

KW = dict(link_radius_m=0.35, angle_tol_rad=np.radians(12.0), max_neighbors=24, split_spread_m=0.25)


def assert_same_partition(labels: np.ndarray, truth: np.ndarray) -> None:
    """Each found cluster holds one true corner and each true corner is one cluster."""
    pairs = np.unique(np.column_stack([labels, truth]), axis=0)
    assert len(np.unique(pairs[:, 0])) == len(pairs), "a cluster mixes two true corners"
    assert len(np.unique(pairs[:, 1])) == len(pairs), "a true corner was split into several clusters"


def test_known_corners_cluster_back_including_close_pairs():
    corners = true_corners()
    en, theta, truth = scatter_enu(corners, n_per=60, seed=1)
    labels = cluster_observations(en, theta, **KW)
    assert_same_partition(labels, truth)
    assert labels.max() + 1 == len(corners)


def test_without_the_angle_gate_the_co_located_pair_would_merge():
    """Cross-check of the oracle: the 0.2 m pair only separates because the walls differ."""
    corners = true_corners()[5:7]
    en, theta, truth = scatter_enu(corners, n_per=60, seed=2)
    same_angles = np.repeat(corners[:1, 2:], len(en), axis=0)
    assert cluster_observations(en, same_angles, **KW).max() == 0
    assert_same_partition(cluster_observations(en, theta, **KW), truth)


def test_angles_across_the_wrap_and_swapped_pairs_still_link():
    corner = np.array([[0.0, 0.0, np.radians(179.5), np.radians(269.5)]])
    en, theta, _ = scatter_enu(corner, n_per=80, seed=3, sigma_angle_rad=np.radians(2.0))
    theta = theta + 2 * np.pi * np.random.default_rng(4).integers(-2, 3, theta.shape)  # any representative
    assert cluster_observations(en, theta, **KW).max() == 0


def test_chained_corners_are_split_at_the_gap():
    """Two same-direction corners 1.2 m apart joined by a thin line of stray observations become two."""
    rng = np.random.default_rng(5)
    a = rng.normal([0.0, 0.0], 0.03, (200, 2))
    b = rng.normal([1.2, 0.0], 0.03, (200, 2))
    bridge = np.column_stack([np.linspace(0.1, 1.1, 6), np.zeros(6)])
    en = np.vstack([a, b, bridge])
    theta = np.tile([0.0, np.pi / 2], (len(en), 1))
    labels = cluster_observations(en, theta, **KW)
    assert labels[0] != labels[200]
    assert len(set(labels[:200])) == 1 and len(set(labels[200:400])) == 1


def test_one_wide_gaussian_is_not_split():
    rng = np.random.default_rng(6)
    en = rng.normal([0.0, 0.0], [0.3, 0.05], (400, 2))
    labels = split_spread_clusters(en, np.zeros(400, np.int64), split_spread_m=0.25)
    assert labels.max() == 0


@pytest.mark.parametrize("workers", [1, 2])
def test_partitioning_neither_splits_nor_duplicates_a_border_cluster(workers):
    corners = true_corners()  # corner 4 sits at east 99.9 m, its observations straddle the 100 m border
    en, theta, truth = scatter_enu(corners, n_per=50, seed=7, sigma_m=0.08)
    straddle = truth == 4
    assert np.any(en[straddle, 0] >= 100.0) and np.any(en[straddle, 0] < 100.0)
    labels, report = cluster_partitioned(en, theta, cell_size_m=100.0, halo_m=5.0, link_radius_m=0.35,
                                         workers=workers, cluster=lambda e, t: cluster_observations(e, t, **KW))
    assert report.n_cells >= 2 and report.n_conflicts == 0 and report.n_wide_clusters == 0
    assert_same_partition(labels, truth)
    single = cluster_observations(en, theta, **KW)
    assert_same_partition(labels, single)


def test_partitioning_reports_a_halo_too_small():
    corners = np.array([[99.9, 0.0, 0.0, np.pi / 2]])
    en, theta, _ = scatter_enu(corners, n_per=50, seed=8, sigma_m=0.3)
    _, report = cluster_partitioned(en, theta, cell_size_m=100.0, halo_m=0.4, link_radius_m=0.35, workers=1,
                                    cluster=lambda e, t: cluster_observations(e, t, **{**KW, "link_radius_m": 1.0}))
    assert report.n_wide_clusters + report.n_conflicts > 0
