"""Loop-closure candidates (proximity on the current estimate, separated in time or from another drive) and
their verification by ICP with fitness, residual, correction and two-start consistency gates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from stages.common.geometry import se3_inverse
from stages.common.registration import floor_information, register_coarse_to_fine, score_alignment


@dataclass(frozen=True)
class Candidate:
    i: int  # the earlier (or map) pose index
    j: int
    prior_distance_m: float


@dataclass(frozen=True)
class Verdict:
    accepted: bool
    reason: str
    T_i_j: np.ndarray
    fitness: float
    inlier_rmse_m: float
    information: np.ndarray


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


def verify_loop(points_i_vehicle: np.ndarray, points_j_vehicle: np.ndarray, T_i_j_prior: np.ndarray, *,
                voxel_m: float, max_corr_m: float, min_fitness: float, max_rmse_m: float,
                max_correction_m: float, max_correction_rad: float, consistency_m: float,
                min_sigma_m: float, min_sigma_rad: float, coarse_voxel_m: float = 1.0,
                coarse_corr_m: float = 3.0, inlier_m: float = 1.0,
                plane_tol_m: float = 0.1) -> Verdict:
    """Coarse-to-fine GICP of scan j onto scan i from the prior relative pose (1-2 m off between passes), and
    again from a start shifted by 1 m along and 0.7 m across; accepted only when both agree, at least
    ``min_fitness`` of the scan lies on the other scan's surfaces (``score_alignment``) with a point-to-plane
    RMS below ``max_rmse_m``, and the correction stays inside the prior's envelope. ``Verdict.fitness`` and
    ``inlier_rmse_m`` are that inlier share and plane RMS."""
    stages = ((coarse_voxel_m, coarse_corr_m), (voxel_m, max_corr_m), (voxel_m, max_corr_m / 2))
    reg = dict(stages=stages, max_iterations=40, min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad)
    res, source, target = register_coarse_to_fine(points_j_vehicle, points_i_vehicle, T_i_j_prior, **reg)
    T = res.T_target_source
    score = score_alignment(source, target, T, inlier_m, plane_tol_m)
    correction = se3_inverse(T_i_j_prior) @ T
    corr_m = float(np.linalg.norm(correction[:3, 3]))
    corr_rad = float(np.arccos(np.clip((np.trace(correction[:3, :3]) - 1) / 2, -1, 1)))
    info = floor_information(res.information, min_sigma_m, min_sigma_rad)
    reason = "accepted"
    if not res.converged or score.inlier_share < min_fitness:
        reason = f"inlier share {score.inlier_share:.2f} < {min_fitness:.2f}"
    elif score.plane_rmse_m > max_rmse_m:
        reason = f"point-to-plane rmse {score.plane_rmse_m:.3f} m > {max_rmse_m:.3f} m"
    elif corr_m > max_correction_m or corr_rad > max_correction_rad:
        reason = f"correction {corr_m:.2f} m / {np.rad2deg(corr_rad):.1f} deg beyond the prior's envelope"
    else:
        shifted = T_i_j_prior.copy()
        shifted[:3, 3] += T_i_j_prior[:3, :3] @ np.array([1.0, -0.7, 0.0])
        res2, _, _ = register_coarse_to_fine(points_j_vehicle, points_i_vehicle, shifted, **reg)
        gap_m = float(np.linalg.norm(res2.T_target_source[:3, 3] - T[:3, 3]))
        if gap_m > consistency_m:
            reason = f"ambiguous: two ICP starts disagree by {gap_m:.2f} m"
    return Verdict(reason == "accepted", reason, T, score.inlier_share, score.plane_rmse_m, info)
