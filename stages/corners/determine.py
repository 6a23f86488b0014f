"""Corner determination (Im et al. 2016 s.2.2.4): the multi-layer redundancy check.

Candidates of different layers that lie within a radius in the horizontal plane and agree on both wall
directions form one corner when at least ``min_layers`` distinct layers contribute. The position is the
information-weighted mean; the covariance is the information-combined covariance plus the scatter of the
candidates about the mean divided by their count (layers see the same wall, so their errors are not fully
independent: the scatter term keeps the combined covariance honest), plus an error common to all layers that
grows with range (a residual angular error of the scan). Every eigenvalue is floored.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from stages.corners.candidates import CornerCandidates


@dataclass(frozen=True)
class Corners:
    """N corners of one scan in the sensor frame (x forward, y left)."""

    x_m: np.ndarray
    y_m: np.ndarray
    theta1_rad: np.ndarray
    theta2_rad: np.ndarray
    cov_m2: np.ndarray  # (N, 2, 2)
    n_layers: np.ndarray
    range_m: np.ndarray
    interior_angle_rad: np.ndarray
    convex: np.ndarray
    time_offset_s: np.ndarray  # mean time of the corner's points after the scan start (NaN when unknown)

    def __len__(self) -> int:
        return int(self.x_m.size)

    def take(self, index: np.ndarray) -> "Corners":
        return Corners(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @classmethod
    def empty(cls) -> "Corners":
        z = np.zeros(0)
        return cls(z, z, z, z, np.zeros((0, 2, 2)), np.zeros(0, np.int16), z, z, np.zeros(0, bool), z)


_DENSE_MAX = 400  # candidates per scan up to which a dense adjacency is cheaper than scipy's sparse graph


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + np.pi) % (2.0 * np.pi) - np.pi)


def _group_sum(group: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """Sum the rows of ``values`` (n, c) by group id -> (n_groups, c)."""
    return np.column_stack([np.bincount(group, values[:, c], minlength=n_groups) for c in range(values.shape[1])])


def floor_covariance(cov_m2: np.ndarray, min_sigma_m: float) -> np.ndarray:
    """Symmetrise and clamp every eigenvalue to >= min_sigma_m^2 (always positive definite)."""
    sym = 0.5 * (cov_m2 + np.swapaxes(cov_m2, -1, -2))
    w, v = np.linalg.eigh(sym)
    w = np.maximum(np.nan_to_num(w, nan=min_sigma_m ** 2), min_sigma_m ** 2)
    return np.einsum("nik,nk,njk->nij", v, w, v)


def cluster_candidates(cand: CornerCandidates, *, cluster_radius_m: float, cluster_max_angle_rad: float
                       ) -> np.ndarray:
    """Connected components of candidates linked when nearer than the radius with matching wall directions."""
    m = len(cand)
    if m == 0:
        return np.zeros(0, np.int64)
    i, j = np.triu_indices(m, k=1)
    close = ((np.hypot(cand.x_m[i] - cand.x_m[j], cand.y_m[i] - cand.y_m[j]) < cluster_radius_m)
             & (_angle_diff(cand.theta1_rad[i], cand.theta1_rad[j]) < cluster_max_angle_rad)
             & (_angle_diff(cand.theta2_rad[i], cand.theta2_rad[j]) < cluster_max_angle_rad))
    if m > _DENSE_MAX:
        graph = coo_matrix((np.ones(close.sum()), (i[close], j[close])), shape=(m, m))
        return connected_components(graph, directed=False)[1]
    adj = np.eye(m, dtype=bool)
    adj[i[close], j[close]] = True
    adj[j[close], i[close]] = True
    label = np.arange(m)
    while True:  # min-label propagation; converges in (component diameter) steps
        new = np.where(adj, label[None, :], m).min(axis=1)
        if np.array_equal(new, label):
            break
        label = new
    return np.unique(label, return_inverse=True)[1]


def determine_corners(cand: CornerCandidates, *, cluster_radius_m: float, cluster_max_angle_rad: float,
                      min_layers: int, min_sigma_m: float, time_offset_s: np.ndarray | None = None,
                      angular_sigma_rad: float = 0.0) -> tuple[Corners, np.ndarray]:
    """Redundancy check and fusion. Returns the corners and, per candidate, its corner index (-1: dropped).

    ``time_offset_s``: per candidate, the time of its points after the scan start (averaged per corner), so a
    consumer can take the vehicle pose at the corner's own time instead of deskewing the scan.
    ``angular_sigma_rad``: an angular error common to all layers of the scan (deskew residual, azimuth jitter),
    added after fusion as an isotropic (range * sigma)^2 term."""
    label = cluster_candidates(cand, cluster_radius_m=cluster_radius_m, cluster_max_angle_rad=cluster_max_angle_rad)
    if label.size == 0:
        return Corners.empty(), label
    n_clusters = int(label.max()) + 1
    pairs = np.unique(np.column_stack([label, cand.layer]), axis=0)
    n_layers = np.bincount(pairs[:, 0], minlength=n_clusters)
    keep_cluster = n_layers >= min_layers
    new_id = np.full(n_clusters, -1)
    new_id[keep_cluster] = np.arange(keep_cluster.sum())
    corner_of = new_id[label]
    sel = corner_of >= 0
    k = int(keep_cluster.sum())
    if k == 0:
        return Corners.empty(), corner_of
    g = corner_of[sel]
    cov = floor_covariance(cand.cov_m2[sel], min_sigma_m)
    info = np.linalg.inv(cov)
    xy = np.column_stack([cand.x_m[sel], cand.y_m[sel]])
    info_sum = _group_sum(g, info.reshape(-1, 4), k).reshape(k, 2, 2)
    info_xy = _group_sum(g, np.einsum("nij,nj->ni", info, xy), k)
    cov_info = np.linalg.inv(info_sum)
    mean = np.einsum("kij,kj->ki", cov_info, info_xy)
    count = np.bincount(g, minlength=k).astype(float)
    dev = xy - mean[g]
    scatter = _group_sum(g, np.einsum("ni,nj->nij", dev, dev).reshape(-1, 4), k).reshape(k, 2, 2)
    common = (np.hypot(mean[:, 0], mean[:, 1]) * angular_sigma_rad) ** 2
    cov_out = floor_covariance(cov_info + scatter / (count * np.maximum(count - 1.0, 1.0))[:, None, None]
                               + common[:, None, None] * np.eye(2), min_sigma_m)

    def circular_mean(theta: np.ndarray) -> np.ndarray:
        s = np.bincount(g, np.sin(theta[sel]), minlength=k)
        c = np.bincount(g, np.cos(theta[sel]), minlength=k)
        return np.arctan2(s, c)

    convex_votes = np.bincount(g, cand.convex[sel].astype(float), minlength=k)
    return Corners(
        x_m=mean[:, 0], y_m=mean[:, 1], theta1_rad=circular_mean(cand.theta1_rad),
        theta2_rad=circular_mean(cand.theta2_rad), cov_m2=cov_out,
        n_layers=n_layers[keep_cluster].astype(np.int16), range_m=np.hypot(mean[:, 0], mean[:, 1]),
        interior_angle_rad=np.bincount(g, cand.interior_angle_rad[sel], minlength=k) / count,
        convex=convex_votes * 2.0 >= count,
        time_offset_s=(np.bincount(g, time_offset_s[sel], minlength=k) / count if time_offset_s is not None
                       else np.full(k, np.nan)),
    ), corner_of
