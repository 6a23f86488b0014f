"""Data association of extracted corners with map corners (Im et al. 2016 s.3.3).

A pair (extracted corner m, map corner k) is accepted when
1. the Mahalanobis distance of the range/bearing innovation is inside a chi-square gate, with the innovation
   covariance ``S = H_k P H_k^T + J_k C_k J_k^T + R_m`` built from the vehicle covariance P, the map corner's
   2x2 ENU covariance C_k and the extracted corner's 2x2 covariance R_m (converted to range/bearing), and
2. both wall direction angles of the extracted corner, rotated into ENU by the estimated yaw, agree with the
   map corner's within a tolerance. The two walls are unordered, so the pair is compared as a set.
Among the accepted pairs a one-to-one assignment is chosen: global nearest neighbour (Hungarian,
``scipy.optimize.linear_sum_assignment``) or greedy nearest neighbour.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.geometry import wrap_angle_rad
from stages.evaluate.ekf import map_corner_jacobian, predict_range_bearing

_INFEASIBLE = 1e12


@dataclass(frozen=True)
class Association:
    meas_idx: np.ndarray  # (A,) index into the extracted corners
    map_idx: np.ndarray  # (A,) index into the map corners given
    z_meas: np.ndarray  # (A,2) measured range_m, bearing_rad
    R_blocks: np.ndarray  # (A,2,2) extraction + map-corner noise in range/bearing (without H P H^T)
    d2: np.ndarray  # (A,) Mahalanobis distance squared
    R_map_blocks: np.ndarray  # (A,2,2) the map-corner part of R_blocks (shared by every epoch using the corner)


def range_bearing_of_points(xy_vehicle_m: np.ndarray, cov_vehicle_m2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame points (M,2) with covariances (M,2,2) -> (M,2) range/bearing and (M,2,2) covariances."""
    p = np.asarray(xy_vehicle_m, dtype=float).reshape(-1, 2)
    r2 = np.maximum(np.einsum("ij,ij->i", p, p), 1e-12)
    r = np.sqrt(r2)
    z = np.column_stack([r, np.arctan2(p[:, 1], p[:, 0])])
    J = np.empty((len(p), 2, 2))
    J[:, 0, 0] = p[:, 0] / r
    J[:, 0, 1] = p[:, 1] / r
    J[:, 1, 0] = -p[:, 1] / r2
    J[:, 1, 1] = p[:, 0] / r2
    return z, J @ np.asarray(cov_vehicle_m2, dtype=float).reshape(-1, 2, 2) @ J.transpose(0, 2, 1)


def direction_set_difference_rad(dirs_a_rad: np.ndarray, dirs_b_rad: np.ndarray) -> np.ndarray:
    """Worst-wall angle difference between unordered direction pairs: (M,2) x (K,2) -> (M,K) radians."""
    a = np.asarray(dirs_a_rad, dtype=float)[:, None, :]
    b = np.asarray(dirs_b_rad, dtype=float)[None, :, :]
    direct = np.maximum(np.abs(wrap_angle_rad(a[..., 0] - b[..., 0])), np.abs(wrap_angle_rad(a[..., 1] - b[..., 1])))
    swap = np.maximum(np.abs(wrap_angle_rad(a[..., 0] - b[..., 1])), np.abs(wrap_angle_rad(a[..., 1] - b[..., 0])))
    return np.minimum(direct, swap)


def wall_headings_rad(dirs_vehicle_rad: np.ndarray, map_dirs_enu_rad: np.ndarray) -> np.ndarray:
    """Heading implied by each wall of associated pairs: (A,2) vehicle-frame and (A,2) ENU directions ->
    (A,2) yaw_enu_rad, walls paired in the order (direct or swapped) that agrees best."""
    a = np.asarray(dirs_vehicle_rad, dtype=float).reshape(-1, 2)
    b = np.asarray(map_dirs_enu_rad, dtype=float).reshape(-1, 2)
    direct = wrap_angle_rad(b - a)
    swapped = wrap_angle_rad(b[:, ::-1] - a)
    spread_direct = np.abs(wrap_angle_rad(direct[:, 0] - direct[:, 1]))
    spread_swapped = np.abs(wrap_angle_rad(swapped[:, 0] - swapped[:, 1]))
    return np.where((spread_swapped < spread_direct)[:, None], swapped, direct)


def _inverse_2x2(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    inv = np.empty_like(S)
    inv[..., 0, 0] = S[..., 1, 1]
    inv[..., 1, 1] = S[..., 0, 0]
    inv[..., 0, 1] = -S[..., 0, 1]
    inv[..., 1, 0] = -S[..., 1, 0]
    return inv / det[..., None, None], det


def gate_costs(q: np.ndarray, P: np.ndarray, z_meas: np.ndarray, R_meas: np.ndarray, dirs_meas_vehicle_rad: np.ndarray,
               map_en_m: np.ndarray, map_cov_m2: np.ndarray, map_dirs_enu_rad: np.ndarray,
               gate_chi2: float, angle_tol_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(M,K) Mahalanobis costs (``inf`` where either gate fails) and (K,2,2) map-corner noise in range/bearing."""
    z_pred, H = predict_range_bearing(q, map_en_m)
    Hk = H.reshape(-1, 2, 3)
    Jm = map_corner_jacobian(H)
    R_map = Jm @ np.asarray(map_cov_m2, dtype=float).reshape(-1, 2, 2) @ Jm.transpose(0, 2, 1)
    S_pred = Hk @ P @ Hk.transpose(0, 2, 1) + R_map  # (K,2,2)
    S = S_pred[None, :, :, :] + R_meas[:, None, :, :]  # (M,K,2,2)
    nu = z_meas[:, None, :] - z_pred[None, :, :]
    nu[..., 1] = wrap_angle_rad(nu[..., 1])
    S_inv, det = _inverse_2x2(S)
    d2 = np.einsum("mki,mkij,mkj->mk", nu, S_inv, nu)
    dirs_enu = wrap_angle_rad(np.asarray(dirs_meas_vehicle_rad, dtype=float) + q[2])
    ang = direction_set_difference_rad(dirs_enu, map_dirs_enu_rad)
    ok = (d2 <= gate_chi2) & (ang <= angle_tol_rad) & (det > 0)
    return np.where(ok, d2, np.inf), R_map


def assign(costs: np.ndarray, method: str = "gnn") -> tuple[np.ndarray, np.ndarray]:
    """One-to-one assignment on finite costs: ``gnn`` (Hungarian) or ``nn`` (greedy by increasing cost)."""
    if costs.size == 0 or not np.isfinite(costs).any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if method == "gnn":
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(np.where(np.isfinite(costs), costs, _INFEASIBLE))
        keep = np.isfinite(costs[rows, cols])
        return rows[keep].astype(np.int64), cols[keep].astype(np.int64)
    if method != "nn":
        from pipeline.errors import ConfigError

        raise ConfigError("association", [f"method: expected 'gnn' or 'nn', got {method!r}"])
    order = np.argsort(costs, axis=None)
    order = order[np.isfinite(costs.ravel()[order])]
    used_r, used_c, rows, cols = set(), set(), [], []
    for flat in order:  # only the few gated candidates of one scan
        r, c = divmod(int(flat), costs.shape[1])
        if r not in used_r and c not in used_c:
            used_r.add(r), used_c.add(c), rows.append(r), cols.append(c)
    return np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)


def associate(q: np.ndarray, P: np.ndarray, xy_vehicle_m: np.ndarray, cov_vehicle_m2: np.ndarray,
              dirs_vehicle_rad: np.ndarray, map_en_m: np.ndarray, map_cov_m2: np.ndarray,
              map_dirs_enu_rad: np.ndarray, *, sensor_range_m: float, gate_chi2: float, angle_tol_rad: float,
              method: str,
              noise_floor_rb: np.ndarray | None = None) -> Association:
    """Associate M extracted corners (vehicle frame) with the map corners in sensor range of the estimate.

    ``noise_floor_rb`` (2x2) is added to every extracted corner's range/bearing covariance (extractor
    covariances from a few layers are optimistic).
    """
    xy = np.asarray(xy_vehicle_m, dtype=float).reshape(-1, 2)
    map_en = np.asarray(map_en_m, dtype=float).reshape(-1, 2)
    empty = Association(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)),
                        np.zeros(0), np.zeros((0, 2, 2)))
    if len(xy) == 0 or len(map_en) == 0:
        return empty
    near = np.flatnonzero(np.hypot(*(map_en - q[:2]).T) <= sensor_range_m)
    if len(near) == 0:
        return empty
    z_meas, R_meas = range_bearing_of_points(xy, cov_vehicle_m2)
    if noise_floor_rb is not None:
        R_meas = R_meas + noise_floor_rb
    costs, R_map = gate_costs(q, P, z_meas, R_meas, np.asarray(dirs_vehicle_rad, dtype=float).reshape(-1, 2),
                              map_en[near], np.asarray(map_cov_m2, dtype=float).reshape(-1, 2, 2)[near],
                              np.asarray(map_dirs_enu_rad, dtype=float).reshape(-1, 2)[near],
                              gate_chi2, angle_tol_rad)
    rows, cols = assign(costs, method)
    return Association(rows, near[cols], z_meas[rows], R_meas[rows] + R_map[cols], costs[rows, cols], R_map[cols])
