"""Pairwise consistency of loop closures (PCM, Mangelson et al. 2018): two loops (i1, j1) and (i2, j2) agree when
the cycle i1 -> j1 (loop 1) -> j2 (odometry) -> i2 (loop 2 backwards) -> i1 (odometry) closes within its
covariance; the loops kept are the largest set that agree pairwise (a maximum clique of the consistency graph,
found greedily from each of the best-connected loops), each confirmed by another loop nearby. One wrong loop agrees
with few others, so it is left out however well its scans matched.

The odometry's relative poses come from the pass-1 estimate (odometry and what loosely holds it); the covariance of
each odometry segment from ``uncertainty.ChainCovariance`` (its position part at the segment's end, its heading
part turning the loop's offset), plus the two loops' own (floored at ``LOOP_SIGMA_M``, ``LOOP_SIGMA_DEG``).
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from stages.common.geometry import se3_inverse
from stages.posegraph.loops.uncertainty import ChainCovariance

LOOP_SIGMA_M = 0.3  # a verified loop's position error beyond its ICP covariance (a street seen from two lanes)
LOOP_SIGMA_DEG = 1.0


def _yaw(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


def _segment(chain: ChainCovariance, a: int, b: int) -> tuple[np.ndarray, float]:
    """(2,2) position covariance and heading variance of the odometry from a to b (one drive; else from starts)."""
    if chain.group[a] == chain.group[b]:
        lo, hi = min(a, b), max(a, b)
        return chain.same_drive(a, np.array([b]))[0], float(chain.s0[hi] - chain.s0[lo])
    cov = chain.from_start(np.array([a, b]))
    yaw = sum(float(chain.s0[x] - chain.s0[chain.start[x]] + chain.start_var_rad2[x]) for x in (a, b))
    return cov[0] + cov[1], yaw


def cycle_error(l1, l2, poses: np.ndarray, chain: ChainCovariance) -> float:
    """Squared Mahalanobis distance (3 dof: east, north, heading) of the cycle of loops ``l1`` and ``l2``."""
    O_i = se3_inverse(poses[l1.i]) @ poses[l2.i]
    O_j = se3_inverse(poses[l1.j]) @ poses[l2.j]
    E = l1.T_i_j @ O_j @ se3_inverse(l2.T_i_j) @ se3_inverse(O_i)  # identity when both loops and the odometry agree
    R1 = poses[l1.i, :2, :2]
    e = np.array([*(R1 @ E[:2, 3]), (_yaw(E) + np.pi) % (2 * np.pi) - np.pi])
    cov_i, yaw_i = _segment(chain, l1.i, l2.i)
    cov_j, yaw_j = _segment(chain, l1.j, l2.j)
    lever = np.linalg.norm(l2.T_i_j[:2, 3]) + np.linalg.norm(l1.T_i_j[:2, 3])
    yaw_var = yaw_i + yaw_j + 2 * np.radians(LOOP_SIGMA_DEG) ** 2
    cov = np.zeros((3, 3))
    cov[:2, :2] = cov_i + cov_j + (2 * LOOP_SIGMA_M ** 2 + yaw_var * lever ** 2) * np.eye(2)
    cov[2, 2] = yaw_var
    return float(e @ np.linalg.solve(cov, e))


def consistency_matrix(loops: list, poses: np.ndarray, chain: ChainCovariance, probability: float,
                       travel: np.ndarray, window_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(n,n) bool: which pairs of loops agree (``cycle_error`` within the chi-square ``probability`` gate), and
    (n,n) bool: which pairs were checked. Only pairs whose two odometry segments are each shorter than ``window_m`` of
    travel (on one drive) are checked: over a longer segment the odometry's unmodelled biases (a scale, a heading
    bias) exceed its stated covariance and reject true loops, while its covariance has grown past what a wrong loop
    moves; the others count as agreeing."""
    n = len(loops)
    gate = chi2.ppf(probability, 3)
    ok = np.ones((n, n), dtype=bool)
    checked = np.zeros((n, n), dtype=bool)
    g = chain.group
    for a in range(n):
        la = loops[a]
        for b in range(a + 1, n):
            lb = loops[b]
            if g[la.i] != g[lb.i] or g[la.j] != g[lb.j] or abs(travel[la.i] - travel[lb.i]) > window_m \
                    or abs(travel[la.j] - travel[lb.j]) > window_m:
                continue
            checked[a, b] = checked[b, a] = True
            ok[a, b] = ok[b, a] = cycle_error(la, lb, poses, chain) <= gate
    return ok, checked


def max_clique(ok: np.ndarray, seeds: int = 16) -> list[int]:
    """A large clique of the boolean adjacency ``ok``: from each of the ``seeds`` best-connected nodes, add nodes
    (best-connected first) adjacent to all chosen; the largest such clique (a heuristic of the maximum clique, exact
    on the small graphs of a drive's loops in practice; ties to the lower indices)."""
    n = len(ok)
    if n == 0:
        return []
    degree = ok.sum(axis=1)
    order = np.lexsort((np.arange(n), -degree))
    best: list[int] = []
    for s in order[:seeds]:
        clique = [int(s)]
        member = ok[s].copy()
        for c in order:
            if c != s and member[c]:
                clique.append(int(c))
                member &= ok[c]
        if len(clique) > len(best):
            best = sorted(clique)
    return best


def consistent_set(loops: list, poses: np.ndarray, chain: ChainCovariance, probability: float, travel: np.ndarray,
                   window_m: float, min_support: int = 1) -> set[int]:
    """Indices into ``loops`` of the largest pairwise-consistent set (module docstring) whose members each agree
    with at least ``min_support`` other checked loops of the set (a loop nothing nearby confirms is left out)."""
    ok, checked = consistency_matrix(loops, poses, chain, probability, travel, window_m)
    keep = max_clique(ok)
    while True:
        sub = np.array(keep, np.int64)
        support = (checked[np.ix_(sub, sub)] & ok[np.ix_(sub, sub)]).sum(axis=1) if len(sub) else np.zeros(0)
        drop = [k for k, s in zip(keep, support) if s < min_support]
        if not drop:
            return set(keep)
        keep = [k for k in keep if k not in drop]
