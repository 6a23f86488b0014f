"""Spatial partitioning of the clustering so cells run in parallel without cutting a cluster (pure numpy).

Each square cell of side ``cell_size_m`` clusters the observations inside the cell grown by ``halo_m`` and keeps
exactly the clusters whose centroid lies in the cell (half-open: [lo, hi)). A cluster of diameter D that has any
observation in a cell is seen whole by that cell when ``halo_m >= 2 D + link_radius_m``, so the cell that owns its
centroid keeps it whole and every other cell drops it: no cluster is split or duplicated. Kept clusters that
are too wide for that guarantee are counted and logged.
"""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PartitionReport:
    n_cells: int
    n_wide_clusters: int  # kept clusters wider than the halo guarantee allows
    n_conflicts: int  # observations claimed by two cells (0 when the guarantee holds)


def _cluster_cell(cell: np.ndarray, cell_of: np.ndarray, en_m: np.ndarray, theta_rad: np.ndarray,
                  cell_size_m: float, halo_m: float, link_radius_m: float,
                  cluster: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> tuple[list[np.ndarray], int]:
    lo = cell * cell_size_m - halo_m
    hi = (cell + 1) * cell_size_m + halo_m
    idx = np.flatnonzero(np.all((en_m >= lo) & (en_m < hi), axis=1))
    labels = cluster(en_m[idx], theta_rad[idx])
    n_lab = int(labels.max()) + 1 if len(labels) else 0
    count = np.bincount(labels, minlength=n_lab)
    centroid = np.stack([np.bincount(labels, en_m[idx, a], n_lab) for a in (0, 1)], 1) / count[:, None]
    owned = np.all(np.floor(centroid / cell_size_m).astype(np.int64) == cell, axis=1)
    radius = np.zeros(n_lab)
    np.maximum.at(radius, labels, np.linalg.norm(en_m[idx] - centroid[labels], axis=1))
    n_wide = int(np.sum(owned & (4.0 * radius + link_radius_m > halo_m)))
    order = np.argsort(labels, kind="stable")
    groups = np.split(idx[order], np.cumsum(count)[:-1]) if n_lab else []
    return [g for g, keep in zip(groups, owned) if keep], n_wide


def cluster_partitioned(en_m: np.ndarray, theta_rad: np.ndarray, *, cell_size_m: float, halo_m: float,
                        link_radius_m: float, workers: int,
                        cluster: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> tuple[np.ndarray, PartitionReport]:
    """Run ``cluster(en_m, theta_rad) -> labels`` per cell in parallel threads; return global labels 0..K-1."""
    n = len(en_m)
    labels = np.full(n, -1, np.int64)
    if n == 0:
        return labels, PartitionReport(0, 0, 0)
    cell_of = np.floor(en_m / cell_size_m).astype(np.int64)
    cells = np.unique(cell_of, axis=0)

    def run(cell):
        return _cluster_cell(cell, cell_of, en_m, theta_rad, cell_size_m, halo_m, link_radius_m, cluster)

    if workers > 1 and len(cells) > 1:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="cornermap-cell") as pool:
            results = list(pool.map(run, cells))
    else:
        results = [run(c) for c in cells]
    next_label, n_wide, n_conflicts = 0, 0, 0
    for groups, wide in results:
        n_wide += wide
        for members in groups:
            n_conflicts += int(np.sum(labels[members] >= 0))
            labels[members] = next_label
            next_label += 1
    orphans = np.flatnonzero(labels < 0)  # cannot happen while the halo guarantee holds; keep them as singletons
    labels[orphans] = next_label + np.arange(len(orphans))
    _, labels = np.unique(labels, return_inverse=True)
    report = PartitionReport(len(cells), n_wide, n_conflicts + len(orphans))
    if n_wide or report.n_conflicts:
        log.warning("cornermap partitioning: %d clusters wider than halo_m=%.1f m allows, %d observations "
                    "claimed by two cells or by none; raise halo_m", n_wide, halo_m, report.n_conflicts)
    return labels.astype(np.int64), report
