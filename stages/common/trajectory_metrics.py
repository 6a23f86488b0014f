"""Trajectory accuracy against ground truth (numpy): absolute, relative (KITTI-style), drift, revisit
self-consistency and edge-heading calibration; used by the pose-graph and odometry benches and tests.

All functions take matching (N,4,4) ``T_map_vehicle`` arrays (estimate, truth) of the same scans.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from stages.common.geometry import se3_inverse, wrap_angle_rad


def horizontal_errors_m(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(T_est[:, :2, 3] - T_true[:, :2, 3], axis=1)


def vertical_errors_m(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return T_est[:, 2, 3] - T_true[:, 2, 3]


def _ypr(T: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(T[:, :3, :3]).as_euler("ZYX")  # yaw, pitch, roll


def heading_errors_rad(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return wrap_angle_rad(_ypr(T_est)[:, 0] - _ypr(T_true)[:, 0])


def pitch_errors_rad(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    return wrap_angle_rad(_ypr(T_est)[:, 1] - _ypr(T_true)[:, 1])


def rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def revisit_pairs(T_true: np.ndarray, stamps_s: np.ndarray, radius_m: float = 2.0, min_dt_s: float = 60.0,
                  max_pairs: int = 200_000, seed: int = 0) -> np.ndarray:
    """(M,2) scan pairs within ``radius_m`` of each other in truth (horizontal) and ``min_dt_s`` apart.

    With several drives, concatenate them and give each drive a time offset larger than ``min_dt_s``.
    """
    pairs = cKDTree(T_true[:, :2, 3]).query_pairs(radius_m, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    pairs = pairs[np.abs(stamps_s[pairs[:, 0]] - stamps_s[pairs[:, 1]]) >= min_dt_s]
    if len(pairs) > max_pairs:
        pairs = pairs[np.random.default_rng(seed).choice(len(pairs), max_pairs, replace=False)]
    return pairs


def self_consistency_errors_m(T_est: np.ndarray, T_true: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Horizontal difference of the pairs' relative position (ENU), estimated vs true: do passes agree?"""
    d_est = T_est[pairs[:, 1], :2, 3] - T_est[pairs[:, 0], :2, 3]
    d_true = T_true[pairs[:, 1], :2, 3] - T_true[pairs[:, 0], :2, 3]
    return np.linalg.norm(d_est - d_true, axis=1)


def self_consistency_heading_errors_rad(T_est: np.ndarray, T_true: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Relative heading of the pairs, estimated vs true: do passes agree in direction? (A heading error shared
    by both passes, e.g. the map frame's own rotation, cancels.)"""
    h = heading_errors_rad(T_est, T_true)
    return wrap_angle_rad(h[pairs[:, 1]] - h[pairs[:, 0]])


def pairs_at_travel(T_true: np.ndarray, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Scan pairs (i, j): j is the first scan ``distance_m`` of (3-D) travel after i, for every i that has one."""
    step = np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1)
    travel = np.concatenate([[0.0], np.cumsum(step)])
    j = np.searchsorted(travel, travel + distance_m)
    i = np.flatnonzero(j < len(travel))
    return i, j[i]


def _relative_poses(T: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(n,4,4) T_i^-1 T_j."""
    return np.einsum("nab,nbc->nac", np.array([se3_inverse(A) for A in T[i]]), T[j])


def relative_error_vectors_m(T_est: np.ndarray, T_true: np.ndarray, distance_m: float = 10.0) -> np.ndarray:
    """(n,3) translation error of the relative pose over ``distance_m`` of travel (KITTI style, body frame)."""
    i, j = pairs_at_travel(T_true, distance_m)
    if len(i) == 0:
        return np.zeros((0, 3))
    rel_true, rel_est = _relative_poses(T_true, i, j), _relative_poses(T_est, i, j)
    err = np.einsum("nab,nbc->nac", np.array([se3_inverse(T) for T in rel_true]), rel_est)
    return err[:, :3, 3]


def relative_errors_m(T_est: np.ndarray, T_true: np.ndarray, distance_m: float = 10.0,
                      horizontal: bool = False) -> np.ndarray:
    """Norm of ``relative_error_vectors_m``: 3-D, or its x-y part with ``horizontal``."""
    e = relative_error_vectors_m(T_est, T_true, distance_m)
    return np.linalg.norm(e[:, :2] if horizontal else e, axis=1)


def drift_percent(T_est: np.ndarray, T_true: np.ndarray, segment_m: float = 100.0) -> float:
    """Mean horizontal translation error of relative poses over ``segment_m`` segments, % of the length."""
    i, j = pairs_at_travel(T_true, segment_m)
    if len(i) == 0:
        return float("nan")
    rel_true, rel_est = _relative_poses(T_true, i, j), _relative_poses(T_est, i, j)
    err = np.linalg.norm(rel_est[:, :2, 3] - rel_true[:, :2, 3], axis=1)
    return float(100.0 * np.mean(err) / segment_m)


def summarize(T_est: np.ndarray, T_true: np.ndarray, stamps_s: np.ndarray) -> dict[str, float]:
    """The issue's target figures for one trajectory."""
    pairs = revisit_pairs(T_true, stamps_s)
    sc = self_consistency_errors_m(T_est, T_true, pairs)
    h = horizontal_errors_m(T_est, T_true)
    rel = relative_error_vectors_m(T_est, T_true, 10.0)
    return {
        "abs_horizontal_rms_m": rms(h), "abs_horizontal_max_m": float(h.max()) if h.size else float("nan"),
        "self_consistency_rms_m": rms(sc), "n_revisit_pairs": int(len(pairs)),
        "self_consistency_heading_rms_deg": float(np.rad2deg(rms(self_consistency_heading_errors_rad(T_est, T_true,
                                                                                                    pairs)))),
        "relative_10m_rms_m": rms(np.linalg.norm(rel, axis=1)),
        "relative_10m_horizontal_rms_m": rms(np.linalg.norm(rel[:, :2], axis=1)),
        "heading_rms_deg": float(np.rad2deg(rms(heading_errors_rad(T_est, T_true)))),
        "vertical_rms_m": rms(vertical_errors_m(T_est, T_true)),
        "pitch_rms_deg": float(np.rad2deg(rms(pitch_errors_rad(T_est, T_true)))),
        "drift_100m_percent": drift_percent(T_est, T_true, 100.0),
    }


def edge_yaw_calibration(T_edges: np.ndarray, information: np.ndarray, T_true: np.ndarray, i: np.ndarray,
                         j: np.ndarray, bins_deg: tuple[float, ...]) -> list[dict[str, float]]:
    """Heading error of relative-pose edges (scan i -> scan j of the true trajectory ``T_true``) against truth,
    by the edge's true |rotation| (``bins_deg`` edges):
    per bin n, error RMS, the median std the edge's information claims (gtsam order: yaw is tangent index 2 for
    a level vehicle), and the mean NEES of the heading (1 when the model fits). Checks a rotation noise model
    such as odometry's ``rot_sigma_per_rad`` (turns)."""
    rel_true = _relative_poses(T_true, np.asarray(i), np.asarray(j))
    err = np.einsum("nab,nbc->nac", np.array([se3_inverse(A) for A in rel_true]).reshape(-1, 4, 4), T_edges)
    e_rad = np.arctan2(err[:, 1, 0], err[:, 0, 0])
    turn_deg = np.abs(np.rad2deg(np.arctan2(rel_true[:, 1, 0], rel_true[:, 0, 0])))
    sigma_rad = np.sqrt(np.linalg.inv(information)[:, 2, 2]) if len(information) else np.zeros(0)
    out = []
    for lo, hi in zip(bins_deg[:-1], bins_deg[1:]):
        m = (turn_deg >= lo) & (turn_deg < hi)
        if not m.any():
            continue
        out.append({"lo_deg": float(lo), "hi_deg": float(hi), "n": int(m.sum()),
                    "error_rms_deg": float(np.rad2deg(rms(e_rad[m]))),
                    "model_sigma_median_deg": float(np.rad2deg(np.median(sigma_rad[m]))),
                    "nees": float(np.mean((e_rad[m] / sigma_rad[m]) ** 2))})
    return out


def horizontal_covariance_consistency(T_est: np.ndarray, T_true: np.ndarray, cov_xy_m2: np.ndarray
                                      ) -> dict[str, float]:
    """Does a trajectory's stated horizontal covariance (N,2,2) hold its errors against the truth? The RMS the
    covariance states (sqrt of the mean trace), the true horizontal RMS, the mean NEES (2 dof: 2 when the
    covariance is honest) and the share of poses under the chi-square 2-dof 95 % quantile (0.95 when honest). A
    pose graph's marginals feed the map's stored covariance, so this is where an overconfident graph shows."""
    e = T_est[:, :2, 3] - T_true[:, :2, 3]
    cov = np.asarray(cov_xy_m2, dtype=float).reshape(-1, 2, 2)
    if not len(e):
        return {"stated_rms_m": float("nan"), "true_rms_m": float("nan"), "nees_mean": float("nan"),
                "nees_share_q95": float("nan")}
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[:, :, None])[:, :, 0])
    return {"stated_rms_m": float(np.sqrt(np.mean(np.trace(cov, axis1=1, axis2=2)))),
            "true_rms_m": rms(np.linalg.norm(e, axis=1)), "nees_mean": float(np.mean(nees)),
            "nees_share_q95": float(np.mean(nees <= -2.0 * np.log(0.05)))}
