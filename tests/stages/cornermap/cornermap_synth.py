"""Synthetic corner observations with known truth for the corner map tests (not a test module)."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from schemas import SCHEMAS
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse

T_VEHICLE_LIDAR = se3_from_xyz_rpy(0.9, 0.1, 1.8, 0.0, 0.0, 0.03)


def true_corners() -> np.ndarray:
    """(K,4) east, north, theta1, theta2 (canonical: theta2 - theta1 in (0, pi])."""
    return np.array([
        [10.0, 12.0, np.radians(-90), np.radians(0)],
        [12.5, 12.0, np.radians(180), np.radians(-90)],  # 2.5 m from the first, walls differ (paper's Figure 10)
        [40.0, 14.0, np.radians(100), np.radians(190)],  # theta2 crosses +-pi
        [60.0, -12.0, np.radians(0), np.radians(90)],
        [99.9, -13.0, np.radians(45), np.radians(135)],  # sits on the 100 m cell border
        [130.0, 11.0, np.radians(-120), np.radians(-10)],
        [130.2, 11.0, np.radians(60), np.radians(170)],  # 0.2 m from the previous, opposite walls
    ])


def vehicle_poses(n_scans: int, lane_north_m: float, yaw_bias_rad: float = 0.0) -> np.ndarray:
    """(n,4,4) T_map_vehicle driving east along y = lane_north_m from x = -20 to x = 160."""
    x = np.linspace(-20.0, 160.0, n_scans)
    return np.stack([se3_from_xyz_rpy(xi, lane_north_m, 0.0, 0.0, 0.0, yaw_bias_rad) for xi in x])


def observe(corners: np.ndarray, drives: dict[str, float], n_scans: int, seed: int, *, sigma_m: float = 0.03,
            sigma_angle_rad: float = np.radians(1.0), max_range_m: float = 35.0,
            pose_sigma: tuple[float, float, float] = (0.02, 0.02, 0.002)):
    """Observe each true corner from every scan within range -> (corners_per_scan, poses_optimized, drive_info).

    ``drives`` maps drive name -> lane north offset. Observations carry extraction noise (sigma_m, in the lidar
    frame) and the listed pose covariance; the poses themselves are exact, so truth is the oracle.
    """
    rng = np.random.default_rng(seed)
    c_rows, p_rows, d_rows = [], [], []
    for d_i, (drive, lane) in enumerate(drives.items()):
        T_map_vehicle = vehicle_poses(n_scans, lane)
        stamps = (1_000_000_000 * (d_i * 10_000 + np.arange(n_scans))).astype(np.int64)
        cov_pose = np.diag(np.square(pose_sigma))
        for s, T in enumerate(T_map_vehicle):
            T_lidar_map = se3_inverse(T @ T_VEHICLE_LIDAR)
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            p_rows.append({"drive": drive, "scan_id": s, "stamp_ns": int(stamps[s]), "x_m": T[0, 3],
                           "y_m": T[1, 3], "z_m": T[2, 3], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3],
                           "cov_xy_yaw": cov_pose.ravel().tolist()})
            pts = np.column_stack([corners[:, :2], np.zeros(len(corners)), np.ones(len(corners))])
            local = (T_lidar_map @ pts.T).T
            yaw_l = np.arctan2(T_lidar_map[1, 0], T_lidar_map[0, 0])
            rng_m = np.hypot(local[:, 0], local[:, 1])
            for k in np.flatnonzero(rng_m < max_range_m):
                xy = local[k, :2] + rng.normal(0.0, sigma_m, 2)
                th = corners[k, 2:] + yaw_l + rng.normal(0.0, sigma_angle_rad, 2)
                if rng.random() < 0.5:  # the extractor may hand the walls in either order
                    th = th[::-1]
                c_rows.append({"drive": drive, "chunk": s // 50, "scan_id": s, "stamp_ns": int(stamps[s]),
                               "corner_idx": int(k), "x_m": xy[0], "y_m": xy[1],
                               "theta1_rad": float(th[0]), "theta2_rad": float(th[1]),
                               "cov_xx_m2": sigma_m**2, "cov_xy_m2": 0.0, "cov_yy_m2": sigma_m**2,
                               "n_layers": 6, "range_m": float(rng_m[k]),
                               "interior_angle_rad": float(np.mod(corners[k, 3] - corners[k, 2], 2 * np.pi)),
                               "convex": True})
        d_rows.append({"drive": drive, "sensor": "sim", "T_vehicle_lidar": T_VEHICLE_LIDAR.ravel().tolist(),
                       "origin_lat_deg": 37.5, "origin_lon_deg": 127.03, "origin_h_m": 40.0,
                       "n_scans": n_scans, "n_quarantined": 0, "drive_file": f"{drive}/drive.yaml"})
    return (pa.Table.from_pylist(c_rows, schema=SCHEMAS["corners_per_scan"]),
            pa.Table.from_pylist(p_rows, schema=SCHEMAS["poses_optimized"]),
            pa.Table.from_pylist(d_rows, schema=SCHEMAS["drive_info"]))


def scatter_enu(corners: np.ndarray, n_per: int, seed: int, sigma_m: float = 0.03,
                sigma_angle_rad: float = np.radians(1.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations directly in ENU around each corner -> (en (N,2), theta (N,2) random order, truth label)."""
    rng = np.random.default_rng(seed)
    label = np.repeat(np.arange(len(corners)), n_per)
    en = corners[label, :2] + rng.normal(0.0, sigma_m, (len(label), 2))
    theta = corners[label, 2:] + rng.normal(0.0, sigma_angle_rad, (len(label), 2))
    flip = rng.random(len(label)) < 0.5
    theta[flip] = theta[flip][:, ::-1]
    return en, theta, label
