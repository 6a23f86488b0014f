"""Scoring a corner map against simulator truth (pure numpy/scipy; used by the bench and the docs table).

The map lives in the frame of ``poses_optimized``, which may sit decimetres from the true frame where GNSS is
biased; ``local_frame_offset`` estimates, per true corner, the mean offset (optimized - true) of drive 0's poses
within ``radius_m``, and the map is judged against truth shifted by it. Absolute figures are reported beside.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.cornermap.angles import canonicalize_pairs, pair_difference_rad


def local_frame_offset(truth_en_m: np.ndarray, pose_true_en_m: np.ndarray, pose_opt_en_m: np.ndarray,
                       radius_m: float = 50.0) -> np.ndarray:
    """(K,2) mean of (optimized - true) pose positions within radius_m of each corner (0 where none)."""
    delta = pose_opt_en_m - pose_true_en_m
    tree = cKDTree(pose_true_en_m)
    out = np.zeros_like(truth_en_m, dtype=float)
    for k, idx in enumerate(tree.query_ball_point(truth_en_m, radius_m)):  # K corners, each a numpy mean
        if idx:
            out[k] = delta[idx].mean(axis=0)
    return out


def score_corner_map(map_en_m: np.ndarray, map_theta_rad: np.ndarray, truth_en_m: np.ndarray,
                     truth_theta_rad: np.ndarray, eligible: np.ndarray, match_radius_m: float = 0.3) -> dict:
    """Precision, recall over ``eligible`` true corners, position and direction RMS of the matched pairs.

    A map corner is a true positive when a true corner lies within match_radius_m; among several, the one whose
    walls agree best. Its direction error is the larger of the two walls' errors (pair order free).
    """
    if len(map_en_m) == 0:
        return {"n_map": 0, "precision": float("nan"), "recall": 0.0, "rms_pos_m": float("nan"),
                "rms_angle_deg": float("nan"), "n_eligible": int(eligible.sum()), "n_duplicates": 0}
    # candidates within the radius; the match is the one whose walls agree best (truth can hold co-located
    # corners of touching buildings), then the nearest
    k = min(4, len(truth_en_m))
    dist, cand = cKDTree(truth_en_m).query(map_en_m, k=k, distance_upper_bound=match_radius_m)
    dist, cand = dist.reshape(len(map_en_m), k), cand.reshape(len(map_en_m), k)
    valid = cand < len(truth_en_m)
    safe = np.where(valid, cand, 0)
    map_c = canonicalize_pairs(map_theta_rad)
    truth_c = canonicalize_pairs(truth_theta_rad)
    diff_all = np.stack([pair_difference_rad(map_c, truth_c[safe[:, c]])[0] for c in range(k)], 1)
    cost = np.where(valid, diff_all + 1e-3 * dist, np.inf)
    best = np.argmin(cost, axis=1)
    rows = np.arange(len(map_en_m))
    tp = valid[rows, best]
    nearest, dist, diff = safe[rows, best], dist[rows, best], diff_all[rows, best][tp]
    found = np.zeros(len(truth_en_m), bool)
    found[nearest[tp]] = True
    n_dup = int(tp.sum() - len(np.unique(nearest[tp])))
    return {
        "n_map": int(len(map_en_m)), "n_true_positive": int(tp.sum()), "n_duplicates": n_dup,
        "precision": float(tp.mean()),
        "n_eligible": int(eligible.sum()),
        "recall": float(found[eligible].mean()) if eligible.any() else float("nan"),
        "rms_pos_m": float(np.sqrt(np.mean(dist[tp] ** 2))) if tp.any() else float("nan"),
        "rms_angle_deg": float(np.degrees(np.sqrt(np.mean(diff**2)))) if tp.any() else float("nan"),
    }
