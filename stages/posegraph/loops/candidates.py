"""Loop-closure candidates: proximity on the current estimate, separated in time or from another drive."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Candidate:
    i: int  # the earlier (or map) pose index
    j: int
    prior_distance_m: float


def keyframes_by_travel(positions_m: np.ndarray, group: np.ndarray, stride_m: float) -> np.ndarray:
    """Indices spaced ``stride_m`` of travel apart within each group (drive), vectorised per group."""
    keep = []
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        step = np.linalg.norm(np.diff(positions_m[idx, :2], axis=0), axis=1)
        travel = np.concatenate([[0.0], np.cumsum(step)])
        _, first = np.unique(np.floor(travel / stride_m).astype(np.int64), return_index=True)
        keep.append(idx[first])
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, np.int64)


def travel_m(positions_m: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Horizontal distance travelled along the poses, not counting the jumps between groups (drives, in blocks):
    differences are travel within a group."""
    step = np.r_[0.0, np.linalg.norm(np.diff(positions_m[:, :2], axis=0), axis=1)]
    step[np.r_[True, group[1:] != group[:-1]]] = 0.0
    return np.cumsum(step)


def loosely_anchored(query: np.ndarray, anchored: np.ndarray, information_en: np.ndarray, travel: np.ndarray,
                     group: np.ndarray, window_m: float, sigma_m: float) -> np.ndarray:
    """The query poses that the survey anchors do not hold: the horizontal information (``information_en``, (K,2,2)
    in east/north, 1/m^2) of the ``anchored`` poses of their group within ``window_m`` of ``travel`` sums to a std
    above ``sigma_m`` in its weaker direction (lane lines fix the position across the road only: a stretch anchored
    on them alone is held across, not along). Every query pose when ``window_m`` is 0."""
    query, anchored = np.asarray(query, np.int64), np.asarray(anchored, np.int64)
    information_en = np.asarray(information_en, float).reshape(-1, 2, 2)
    if window_m <= 0 or len(query) == 0:
        return query
    keep = np.ones(len(query), bool)
    for g in np.unique(group[query]):
        mine_a = np.flatnonzero(group[anchored] == g)
        if len(mine_a) == 0:
            continue
        order = mine_a[np.argsort(travel[anchored[mine_a]], kind="stable")]
        at = travel[anchored[order]]
        cum = np.concatenate([np.zeros((1, 2, 2)), np.cumsum(information_en[order], axis=0)])
        mine = np.flatnonzero(group[query] == g)
        t = travel[query[mine]]
        info = cum[np.searchsorted(at, t + window_m, side="right")] - cum[np.searchsorted(at, t - window_m, "left")]
        a, b, c = info[:, 0, 0], info[:, 0, 1], info[:, 1, 1]
        weaker = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)  # the smaller eigenvalue
        keep[mine] = weaker < sigma_m ** -2
    return query[keep]


def find_candidates(positions_m: np.ndarray, stamps_s: np.ndarray, group: np.ndarray, query: np.ndarray, *,
                    radius_m: float, min_separation_s: float, max_per_scan: int,
                    allowed_targets: np.ndarray | None = None) -> list[Candidate]:
    """For each query pose, up to ``max_per_scan`` nearest poses of *other passes* within ``radius_m``.

    Another pass = another group (drive), or the same group at least ``min_separation_s`` away in time.
    Targets that are themselves within ``min_separation_s`` of an already chosen target are skipped, so two
    candidates of one query come from two different passes. ``allowed_targets`` (bool mask) restricts the
    targets (e.g. to map drives when localising a reference drive).
    """
    tree = cKDTree(positions_m[:, :2])
    seen: set[tuple[int, int]] = set()
    out: list[Candidate] = []
    for q in query:
        nbrs = np.asarray(tree.query_ball_point(positions_m[q, :2], radius_m), dtype=np.int64)
        if allowed_targets is not None:
            nbrs = nbrs[allowed_targets[nbrs]]
        other = (group[nbrs] != group[q]) | (np.abs(stamps_s[nbrs] - stamps_s[q]) >= min_separation_s)
        nbrs = nbrs[other]
        if len(nbrs) == 0:
            continue
        d = np.linalg.norm(positions_m[nbrs, :2] - positions_m[q, :2], axis=1)
        chosen: list[int] = []
        for k in np.argsort(d):
            t = nbrs[k]
            if any(group[t] == group[c] and abs(stamps_s[t] - stamps_s[c]) < min_separation_s for c in chosen):
                continue
            chosen.append(int(t))
            pair = (min(q, t), max(q, t))
            if pair not in seen:
                seen.add(pair)
                out.append(Candidate(pair[0], pair[1], float(d[k])))
            if len(chosen) >= max_per_scan:
                break
    return out
