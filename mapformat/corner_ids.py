"""Stable corner identity across map versions.

At publish, the new version's corners are matched one-to-one to the previous version's (the map's LATEST):
a pair is admissible when the positions are within ``max_dist_m`` and both wall directions agree within
``max_angle_deg`` (walls compared as an unordered pair: whichever pairing of theta1/theta2 fits better).
Among admissible pairs, the assignment minimising the summed normalised cost
``(dist / max_dist_m)^2 + (wall angle error / max_angle_deg)^2`` is found with the Hungarian method
(``scipy.optimize.linear_sum_assignment``), run per connected component of the admissible-pair graph so a
city-sized map never builds a dense N x M matrix. Matched corners keep the previous id; the others get new
ids from the map's counter (``next_corner_id`` in the manifest), so an id is never reused in a map.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class IdGates:
    """Gates of the corner identity match (published in each changelog)."""

    max_dist_m: float = 1.0
    max_angle_deg: float = 15.0

    def __post_init__(self) -> None:
        for name in ("max_dist_m", "max_angle_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"IdGates.{name} {value}: expected a positive number")


@dataclass(frozen=True)
class IdMatch:
    i_prev: np.ndarray  # (K,) indices into the previous corners
    i_new: np.ndarray  # (K,) indices into the new corners
    dist_m: np.ndarray  # (K,) position distance of each pair
    angle_deg: np.ndarray  # (K,) worse wall-direction error of each pair


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return np.abs((np.degrees(a) + 180.0) % 360.0 - 180.0)


def wall_angle_error_deg(theta_a_rad: np.ndarray, theta_b_rad: np.ndarray) -> np.ndarray:
    """(K,) worse of the two wall-direction errors under the better pairing of the (K, 2) wall angles."""
    a, b = np.asarray(theta_a_rad, float).reshape(-1, 2), np.asarray(theta_b_rad, float).reshape(-1, 2)
    straight = np.maximum(_wrap_deg(a[:, 0] - b[:, 0]), _wrap_deg(a[:, 1] - b[:, 1]))
    crossed = np.maximum(_wrap_deg(a[:, 0] - b[:, 1]), _wrap_deg(a[:, 1] - b[:, 0]))
    return np.minimum(straight, crossed)


def match_corners(prev_en_m: np.ndarray, prev_theta_rad: np.ndarray, new_en_m: np.ndarray,
                  new_theta_rad: np.ndarray, gates: IdGates = IdGates()) -> IdMatch:
    """One-to-one, minimum-cost match of the new corners (M,2)/(M,2) to the previous ones (N,2)/(N,2)."""
    pe, ne = np.asarray(prev_en_m, float).reshape(-1, 2), np.asarray(new_en_m, float).reshape(-1, 2)
    pt, nt = np.asarray(prev_theta_rad, float).reshape(-1, 2), np.asarray(new_theta_rad, float).reshape(-1, 2)
    empty = IdMatch(*(np.zeros(0, np.int64),) * 2, np.zeros(0), np.zeros(0))
    if len(pe) == 0 or len(ne) == 0:
        return empty
    pairs = cKDTree(pe).query_ball_tree(cKDTree(ne), gates.max_dist_m)
    ip = np.repeat(np.arange(len(pe)), [len(p) for p in pairs])
    jn = np.concatenate([np.asarray(p, np.int64) for p in pairs]) if len(ip) else np.zeros(0, np.int64)
    if len(ip) == 0:
        return empty
    dist = np.linalg.norm(pe[ip] - ne[jn], axis=1)
    ang = wall_angle_error_deg(pt[ip], nt[jn])
    ok = (dist <= gates.max_dist_m) & (ang <= gates.max_angle_deg)
    ip, jn, dist, ang = ip[ok], jn[ok], dist[ok], ang[ok]
    if len(ip) == 0:
        return empty
    cost = (dist / gates.max_dist_m) ** 2 + (ang / gates.max_angle_deg) ** 2
    # components of the bipartite admissible graph: nodes 0..N-1 previous, N..N+M-1 new
    n, m = len(pe), len(ne)
    graph = coo_matrix((np.ones(len(ip)), (ip, n + jn)), shape=(n + m, n + m))
    _, label = connected_components(graph, directed=False)
    comp = label[ip]
    order = np.argsort(comp, kind="stable")
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    out_p, out_n = [], []
    for sel in np.split(order, bounds):
        if len(sel) == 1:
            out_p.append(ip[sel])
            out_n.append(jn[sel])
            continue
        rows, r_idx = np.unique(ip[sel], return_inverse=True)
        cols, c_idx = np.unique(jn[sel], return_inverse=True)
        big = 1e6  # inadmissible; never chosen over leaving a corner unmatched (dropped below)
        mat = np.full((len(rows), len(cols)), big)
        mat[r_idx, c_idx] = cost[sel]
        r, c = linear_sum_assignment(mat)
        keep = mat[r, c] < big
        out_p.append(rows[r[keep]])
        out_n.append(cols[c[keep]])
    i_prev, i_new = np.concatenate(out_p), np.concatenate(out_n)
    order = np.argsort(i_new, kind="stable")
    i_prev, i_new = i_prev[order], i_new[order]
    return IdMatch(i_prev, i_new, np.linalg.norm(pe[i_prev] - ne[i_new], axis=1),
                   wall_angle_error_deg(pt[i_prev], nt[i_new]))


def assign_ids(prev_ids: np.ndarray, match: IdMatch, n_new: int, next_id: int,
               new_order: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Ids of the new corners: the previous id where matched, else fresh ids from ``next_id`` upwards, given
    in ``new_order`` (default: index order). Returns (ids (n_new,) int64, the counter after)."""
    ids = np.full(n_new, -1, np.int64)
    ids[match.i_new] = np.asarray(prev_ids, np.int64)[match.i_prev]
    order = np.arange(n_new) if new_order is None else np.asarray(new_order, np.int64)
    fresh = order[ids[order] < 0]
    ids[fresh] = next_id + np.arange(len(fresh), dtype=np.int64)
    return ids, int(next_id + len(fresh))
