"""GNSS position factors and INS attitude priors from per-scan GNSS/INS poses.

Receivers understate their error in street canyons, so the reported std is inflated and the factor gets a
robust kernel; consecutive fixes share a slowly varying bias, so only one factor per ``every_s`` seconds
enters the graph (more would count the same bias many times). Outages (``valid`` false) have no factor.
"""
from __future__ import annotations

import numpy as np

from stages.posegraph.graph import AttitudePrior, PositionPrior


def select_epochs(stamps_ns: np.ndarray, valid: np.ndarray, every_s: float) -> np.ndarray:
    """Indices of valid epochs, at most one per ``every_s`` seconds (0: every valid epoch)."""
    idx = np.flatnonzero(valid)
    if every_s <= 0 or len(idx) == 0:
        return idx
    keep, last_ns = [], None
    gap_ns = every_s * 1e9
    for k, t in zip(idx, stamps_ns[idx]):  # per epoch (not per point): greedy, >= every_s apart
        if last_ns is None or t - last_ns >= gap_ns:
            keep.append(k)
            last_ns = t
    return np.asarray(keep, dtype=np.int64)


def gnss_position_priors(pose_index: np.ndarray, stamps_ns: np.ndarray, T_map_vehicle: np.ndarray,
                         std_enu_m: np.ndarray, valid: np.ndarray, *, every_s: float, inflation: float,
                         min_std_m: float, robust: str, kernel_k: float,
                         lever_arm_m: np.ndarray) -> list[PositionPrior]:
    """One robust position factor per selected epoch; the measured point is the antenna position."""
    lever = np.asarray(lever_arm_m, dtype=float)
    out = []
    for k in select_epochs(stamps_ns, valid, every_s):
        T = T_map_vehicle[k]
        antenna = T[:3, 3] + T[:3, :3] @ lever
        sigma = np.maximum(np.asarray(std_enu_m[k], float) * inflation, min_std_m)
        out.append(PositionPrior(int(pose_index[k]), antenna, sigma, robust, kernel_k, lever))
    return out


def attitude_priors(pose_index: np.ndarray, stamps_ns: np.ndarray, T_map_vehicle: np.ndarray,
                    std_yaw_rad: np.ndarray, valid: np.ndarray, *, every_s: float, roll_pitch_sigma_rad: float,
                    yaw_inflation: float) -> list[AttitudePrior]:
    """INS roll/pitch (gravity) as a firm prior, INS yaw as a weak one; same epochs as the GNSS factors."""
    out = []
    for k in select_epochs(stamps_ns, valid, every_s):
        sigma_yaw = max(float(std_yaw_rad[k]) * yaw_inflation, roll_pitch_sigma_rad)
        out.append(AttitudePrior(int(pose_index[k]), T_map_vehicle[k][:3, :3].copy(),
                                 np.array([roll_pitch_sigma_rad, roll_pitch_sigma_rad, sigma_yaw])))
    return out


def gnss_residuals_enu(T_map_vehicle_est: np.ndarray, priors: list[PositionPrior]) -> np.ndarray:
    """(M,3) estimated antenna position minus GNSS measurement, ENU metres, per factor."""
    if not priors:
        return np.zeros((0, 3))
    out = np.empty((len(priors), 3))
    for n, g in enumerate(priors):
        T = T_map_vehicle_est[g.i]
        out[n] = T[:3, 3] + T[:3, :3] @ g.lever_arm_m - g.position_enu_m
    return out
