"""Merge the clusters that split one physical corner (pure numpy/scipy).

Clustering links observations within ``link_radius_m`` (0.35 m); one corner seen from different sides or
through poses that disagree by a few decimetres can still end up as two clusters ~0.5 m apart with the same
walls, i.e. two map corners a localizer would match to one facade corner. After clustering:

1. Duplicate groups: clusters whose positions lie within ``merge_radius_m`` and whose two wall directions agree
   within ``angle_tol_rad`` (either order), as connected components (the clustering's ``link_graph``).
2. A group's observations are merged into one cluster when the merged cluster passes the map's filter (count,
   spread, covariance, angles): one corner at the information-weighted mean of all of them.
3. Otherwise (merging would make a cluster too spread to keep) the group's members stay apart, and of the ones
   the filter keeps only the strongest survives (most observations first); any other within ``merge_radius_m``
   with matching walls of an already kept one is rejected as ``duplicate``.

So the map never holds two corners within ``merge_radius_m`` whose walls match (checked by ``count_duplicates``).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from stages.cornermap.angles import pair_difference_rad
from stages.cornermap.clustering import link_graph


def duplicate_groups(en_m: np.ndarray, theta_rad: np.ndarray, merge_radius_m: float, angle_tol_rad: float,
                     max_neighbors: int = 24) -> np.ndarray:
    """(K,) group id per cluster: connected components of 'within merge_radius_m with matching walls'."""
    k = len(en_m)
    if k == 0:
        return np.empty(0, np.int64)
    i, j = link_graph(en_m, theta_rad, merge_radius_m, angle_tol_rad, max_neighbors)
    _, group = connected_components(coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(k, k)), directed=False)
    return group.astype(np.int64)


def count_duplicates(en_m: np.ndarray, theta_rad: np.ndarray, radius_m: float = 1.0,
                     angle_tol_rad: float = np.radians(12.0)) -> int:
    """Pairs of corners within ``radius_m`` whose walls agree within ``angle_tol_rad`` (either order)."""
    if len(en_m) < 2:
        return 0
    pairs = np.array(sorted(cKDTree(en_m).query_pairs(radius_m)), np.int64).reshape(-1, 2)
    if not len(pairs):
        return 0
    diff, _ = pair_difference_rad(theta_rad[pairs[:, 0]], theta_rad[pairs[:, 1]])
    return int(np.sum(diff <= angle_tol_rad))


def merge_duplicates(labels: np.ndarray, en_m: np.ndarray, theta_rad: np.ndarray, n_obs: np.ndarray,
                     passes: Callable[[np.ndarray], np.ndarray], *, merge_radius_m: float, angle_tol_rad: float,
                     max_neighbors: int = 24) -> tuple[np.ndarray, np.ndarray, int]:
    """Observation labels after merging duplicate clusters.

    ``labels``: (N,) cluster per observation (0..K-1); ``en_m``, ``theta_rad``, ``n_obs``: the K clusters'
    summaries; ``passes(labels) -> (K',) bool`` runs aggregation and the map's filter on any labelling.
    Returns (new labels 0..K''-1, (K'',) bool 'rejected as duplicate', number of merged groups).
    """
    group = duplicate_groups(en_m, theta_rad, merge_radius_m, angle_tol_rad, max_neighbors)
    k = len(group)
    sizes = np.bincount(group, minlength=int(group.max()) + 1 if k else 0)
    multi = sizes[group] > 1 if k else np.zeros(0, bool)
    if not multi.any():
        return labels, np.zeros(k, bool), 0
    # try every multi-member group merged at once (groups are disjoint, so one aggregation judges them all)
    trial = np.where(multi, k + group, np.arange(k))
    _, trial = np.unique(trial, return_inverse=True)
    ok_trial = passes(trial[labels])
    merge = multi & ok_trial[trial]
    final = np.where(merge, k + group, np.arange(k))
    _, final = np.unique(final, return_inverse=True)
    new_labels = final[labels]
    duplicate = np.zeros(int(final.max()) + 1, bool)
    kept = passes(new_labels)
    for g in np.unique(group[multi & ~merge]):  # groups left apart: keep the strongest kept member, greedily
        members = np.flatnonzero((group == g) & kept[final])
        members = members[np.argsort(-n_obs[members], kind="stable")]
        chosen: list[int] = []
        for m in members:
            near = [c for c in chosen if np.hypot(*(en_m[m] - en_m[c])) <= merge_radius_m
                    and pair_difference_rad(theta_rad[[m]], theta_rad[[c]])[0][0] <= angle_tol_rad]
            if near:
                duplicate[final[m]] = True
            else:
                chosen.append(m)
    n_merged = len(np.unique(group[merge]))
    return new_labels, duplicate, n_merged
