"""Keyframe pairs: two scans further apart in time than ``KeyframeConfig.min_dt_s`` (a drive published as SLAM
keyframes metres apart, or a gap), registered like the wide-baseline pairs they are.

- Start: the pair's reference increment (the prior trajectory's, else the GNSS/INS's); without one, a global
  registration of the two structure clouds (``stages.common.registration_global``: FPFH + RANSAC), never constant
  velocity (the motion between keyframes is not the last pair's).
- Registration: GICP in ``KeyframeConfig.stages`` (voxel m, correspondence m) from that start
  (``registration.register_coarse_to_fine``), on the structure above each scan's road plane.
- Gate: a registration 5 m long is worse than one of 0.5 m (tiny calibration seed 7, every 12th scan, 5.4 m apart,
  started from the truth: 0.08 m and 0.43 deg RMS, up to 0.25 m and 1.1 deg), so the reference's limit grows with
  the pair's distance d: hypot(limit, ``deviation_*_per_m`` x d).
- Information: floored at ``sigma_*_per_m`` x d (the same measurement: 0.015 m and 0.0015 rad per metre).
- Vehicle motion: a car moves along its heading; over a pair turning by t its chord points at t / 2 from the first
  heading (forward or reverse). A pair whose chord leaves that by more than ``max_sideslip_rad`` (15 deg) is
  rejected: without a reference, a global registration matched to a repeated facade (tiny seed 861, every 12th scan:
  22 m backwards and 10 m sideways, fitness 0.30) is caught by nothing else. Pairs under 1 m are not judged.

``bench/bench_keyframes.py`` measures it; docs/posegraph.md, "Keyframe drives", has the figures.
"""
from __future__ import annotations

import numpy as np

from stages.common.ground_plane import split_road
from stages.common.registration import RegistrationResult, floor_information, register_coarse_to_fine
from stages.odometry.config import KeyframeConfig
from stages.odometry.params import OdometryParams
from stages.odometry.prepare import PreparedScan


def structure_points(scan: PreparedScan, T_vehicle_lidar: np.ndarray, tolerance_m: float) -> np.ndarray:
    """The scan's points above its road plane (all its points where it has none)."""
    if scan.plane is None:
        return scan.points_m
    return split_road(scan.points_m, T_vehicle_lidar, tolerance_m).structure_m


def global_guess_l(src: PreparedScan, tgt: PreparedScan, T_vehicle_lidar: np.ndarray, cfg: OdometryParams,
                   seed: int = 0) -> np.ndarray:
    """T_target_source (lidar frame) of a pair with no reference: FPFH + RANSAC on the structure clouds."""
    from stages.common.registration_global import register_global

    kf = cfg.keyframe
    tol = cfg.prepare.ground_tolerance_m
    match = register_global(structure_points(src, T_vehicle_lidar, tol), structure_points(tgt, T_vehicle_lidar, tol),
                            voxel_m=kf.global_voxel_m, normal_radius_m=2.0 * kf.global_voxel_m,
                            feature_radius_m=5.0 * kf.global_voxel_m, max_corr_m=1.5 * kf.global_voxel_m, seed=seed)
    return match.T_target_source


def register_keyframe_pair(src: PreparedScan, tgt: PreparedScan, guess_l: np.ndarray, T_vehicle_lidar: np.ndarray,
                           cfg: OdometryParams) -> RegistrationResult:
    """Coarse-to-fine GICP of the structure clouds from ``guess_l`` (lidar frame)."""
    i = cfg.information
    tol = cfg.prepare.ground_tolerance_m
    res, _, _ = register_coarse_to_fine(structure_points(src, T_vehicle_lidar, tol),
                                        structure_points(tgt, T_vehicle_lidar, tol), guess_l,
                                        stages=cfg.keyframe.stages, max_iterations=cfg.icp.max_iterations,
                                        point_sigma_m=i.point_sigma_m, min_sigma_m=i.min_sigma_m,
                                        min_sigma_rad=i.min_sigma_rad, relative_tolerance=cfg.icp.relative_tolerance)
    return res


def widened_limits(limit_m: float, limit_rad: float, distance_m: float, kf: KeyframeConfig) -> tuple[float, float]:
    """A keyframe pair's gate limits: the reference's, widened with the registration's error over ``distance_m``."""
    return float(np.hypot(limit_m, kf.deviation_m_per_m * distance_m)), \
        float(np.hypot(limit_rad, kf.deviation_rad_per_m * distance_m))


def plausible_motion(T_v: np.ndarray, max_sideslip_rad: float, min_distance_m: float = 1.0) -> bool:
    """Whether a vehicle increment's chord follows its heading: within ``max_sideslip_rad`` of half its turn,
    forward or reverse (module docstring); increments under ``min_distance_m`` always are."""
    dx, dy = float(T_v[0, 3]), float(T_v[1, 3])
    if np.hypot(dx, dy) < min_distance_m:
        return True
    half_turn = 0.5 * np.arctan2(T_v[1, 0], T_v[0, 0])
    off = np.arctan2(dy, dx) - half_turn
    off = (off + np.pi / 2) % np.pi - np.pi / 2  # forward and reverse alike
    return bool(abs(off) <= max_sideslip_rad)


def keyframe_information(info_v: np.ndarray, distance_m: float, kf: KeyframeConfig) -> np.ndarray:
    """An edge's information floored at the keyframe error over ``distance_m``."""
    return floor_information(info_v, max(kf.sigma_m_per_m * distance_m, 1e-6),
                             max(kf.sigma_rad_per_m * distance_m, 1e-9))
