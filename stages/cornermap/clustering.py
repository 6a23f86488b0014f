"""Cluster corner observations of the same physical corner across scans and drives (pure numpy/scipy).

1. Neighbours: a k-nearest-neighbour query (cKDTree) in an embedding of position and the *unordered* pair of
   wall directions: (east, north, s*(u+v), s*u*v) with u = e^{i theta1}, v = e^{i theta2} as complex numbers.
   Both u+v and uv are symmetric in (u, v), so a swapped pair embeds to the same point; s = r / tol makes an
   angle error of ``tol`` weigh about as much as ``r`` metres.
2. Edges: a neighbour is linked only if it lies within ``link_radius_m`` and both wall directions agree within
   ``angle_tol_rad`` (mod 2 pi, either order). Connected components (scipy.sparse.csgraph) are the clusters:
   two corners 2.5 m apart never link, nor two co-located corners whose walls point differently.
3. Split: single linkage can chain two corners through stray observations; a cluster whose principal std
   exceeds ``split_spread_m`` is cut in two along its principal axis when the halves are clearly bimodal
   (Ashman's D > 4), recursively.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

_ASHMAN_D_MIN = 4.0
_MAX_SPLIT_DEPTH = 4


def embed_observations(en_m: np.ndarray, theta_rad: np.ndarray, metres_per_rad: float) -> np.ndarray:
    """(N,2) positions + (N,2) wall directions -> (N,6) order-invariant embedding for neighbour search."""
    u = np.exp(1j * theta_rad[:, 0])
    v = np.exp(1j * theta_rad[:, 1])
    s, p = (u + v) * metres_per_rad, (u * v) * metres_per_rad
    return np.column_stack([en_m, s.real, s.imag, p.real, p.imag])


def link_graph(en_m: np.ndarray, theta_rad: np.ndarray, link_radius_m: float, angle_tol_rad: float,
               max_neighbors: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (i, j) between observations close in position and in both wall directions."""
    n = len(en_m)
    if n < 2:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    feats = embed_observations(en_m, theta_rad, link_radius_m / angle_tol_rad)
    k = min(max_neighbors + 1, n)
    # sqrt(1 + 3): the angle part of the embedding is at most ~sqrt(3) x the angle error in metres.
    _, idx = cKDTree(feats).query(feats, k=k, distance_upper_bound=2.0 * link_radius_m)
    i = np.repeat(np.arange(n), k)
    j = idx.ravel()
    ok = (j < n) & (j != i)  # kNN is not symmetric: keep both directions
    i, j = i[ok], j[ok]
    close = np.sum((en_m[i] - en_m[j]) ** 2, axis=1) <= link_radius_m**2
    i, j = i[close], j[close]
    # both walls agree within tol, as given or swapped: cos(a - b) = u_a . u_b >= cos(tol)
    u = np.stack([np.cos(theta_rad), np.sin(theta_rad)], axis=-1)  # (n, 2 walls, 2)
    dot = lambda a, b: np.einsum("ij,ij->i", u[i, a], u[j, b])  # noqa: E731
    cos_tol = np.cos(angle_tol_rad)
    keep = (np.minimum(dot(0, 0), dot(1, 1)) >= cos_tol) | (np.minimum(dot(0, 1), dot(1, 0)) >= cos_tol)
    return i[keep], j[keep]


def _bimodal_split(points: np.ndarray) -> np.ndarray | None:
    """Boolean mask of one half if the points are clearly two groups along the principal axis, else None."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    x = centred @ vt[0]
    threshold = 0.0
    for _ in range(20):  # 1-D 2-means (Lloyd), starting from the mean
        lo, hi = x[x <= threshold], x[x > threshold]
        if len(lo) < 2 or len(hi) < 2:
            return None
        new = 0.5 * (lo.mean() + hi.mean())
        if abs(new - threshold) < 1e-9:
            break
        threshold = new
    lo, hi = x[x <= threshold], x[x > threshold]
    pooled = np.sqrt(0.5 * (lo.var() + hi.var())) + 1e-9
    ashman_d = np.sqrt(2.0) * abs(hi.mean() - lo.mean()) / (np.sqrt(2.0) * pooled)
    return (x > threshold) if ashman_d > _ASHMAN_D_MIN else None


def split_spread_clusters(en_m: np.ndarray, labels: np.ndarray, split_spread_m: float) -> np.ndarray:
    """Recursively split clusters whose principal std exceeds split_spread_m and that are clearly bimodal."""
    labels = labels.copy()
    next_label = int(labels.max()) + 1 if len(labels) else 0
    for _ in range(_MAX_SPLIT_DEPTH):
        n_lab = next_label
        count = np.bincount(labels, minlength=n_lab).astype(float)
        mean = np.stack([np.bincount(labels, en_m[:, a], n_lab) for a in (0, 1)], 1) / np.maximum(count, 1)[:, None]
        d = en_m - mean[labels]
        sxx = np.bincount(labels, d[:, 0] ** 2, n_lab) / np.maximum(count, 1)
        syy = np.bincount(labels, d[:, 1] ** 2, n_lab) / np.maximum(count, 1)
        sxy = np.bincount(labels, d[:, 0] * d[:, 1], n_lab) / np.maximum(count, 1)
        lam_max = 0.5 * (sxx + syy) + np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
        wide = np.flatnonzero((lam_max > split_spread_m**2) & (count >= 4))
        if len(wide) == 0:
            break
        order = np.argsort(labels, kind="stable")
        starts = np.searchsorted(labels[order], wide)
        changed = False
        for lab, start in zip(wide, starts):  # few clusters: a loop over clusters, not over points
            members = order[start:start + int(count[lab])]
            half = _bimodal_split(en_m[members])
            if half is not None:
                labels[members[half]] = next_label
                next_label += 1
                changed = True
        if not changed:
            break
    return labels


def cluster_observations(en_m: np.ndarray, theta_rad: np.ndarray, *, link_radius_m: float,
                         angle_tol_rad: float, max_neighbors: int, split_spread_m: float) -> np.ndarray:
    """(N,) cluster label per observation, labels 0..K-1."""
    n = len(en_m)
    if n == 0:
        return np.empty(0, np.int64)
    i, j = link_graph(en_m, theta_rad, link_radius_m, angle_tol_rad, max_neighbors)
    graph = coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    labels = split_spread_clusters(en_m, labels.astype(np.int64), split_spread_m)
    _, labels = np.unique(labels, return_inverse=True)
    return labels.astype(np.int64)
