"""Lidar-frame corner observations + optimized vehicle poses -> ENU observations with covariance (pure numpy).

For a corner at ``q`` (x, y, z=0) in the lidar frame and ``T_map_lidar = T_map_vehicle @ T_vehicle_lidar``:

    p_en  = (T_map_lidar @ q)[:2]
    Sigma = J_pose Sigma_pose J_pose^T + A Sigma_corner A^T

with ``A = R_map_lidar[:2, :2]`` (the Jacobian of p_en w.r.t. the lidar x, y) and, for the pose state
(east, north, yaw) of the vehicle, ``J_pose = [[1, 0, -(n - n_v)], [0, 1, e - e_v]]`` (a yaw perturbation
rotates the corner about the vehicle origin). Wall directions are rotated by the same map; the pair is returned
in the canonical order of ``angles.py``. The two covariance parts are returned separately because the pose part
is correlated along a drive and the extraction part is not (see aggregate.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.cornermap.angles import canonicalize_pairs


@dataclass(frozen=True)
class EnuObservations:
    """N corner observations in the map's ENU frame."""

    en_m: np.ndarray  # (N,2) east, north
    theta_enu_rad: np.ndarray  # (N,2) canonical wall directions, CCW from east
    cov_corner_m2: np.ndarray  # (N,2,2) extraction noise rotated into ENU
    cov_pose_m2: np.ndarray  # (N,2,2) pose uncertainty propagated to the corner
    J_pose: np.ndarray | None = None  # (N,2,3) d(east, north) / d(pose east, north, yaw)
    cov_pose_xy_yaw: np.ndarray | None = None  # (N,3,3) the observing pose's covariance

    @property
    def cov_m2(self) -> np.ndarray:
        return self.cov_corner_m2 + self.cov_pose_m2


def covariance_from_components(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """(N,) components -> (N,2,2) symmetric matrices."""
    return np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2)


def transform_to_enu(xy_lidar_m: np.ndarray, theta_lidar_rad: np.ndarray, cov_lidar_m2: np.ndarray,
                     T_map_vehicle: np.ndarray, T_vehicle_lidar: np.ndarray,
                     cov_pose_xy_yaw: np.ndarray) -> EnuObservations:
    """Vectorised over N observations; every per-observation input has a leading N axis.

    xy_lidar_m (N,2); theta_lidar_rad (N,2); cov_lidar_m2 (N,2,2); T_map_vehicle (N,4,4); T_vehicle_lidar
    (N,4,4) or (4,4); cov_pose_xy_yaw (N,3,3) over (east m, north m, yaw rad).
    """
    xy = np.asarray(xy_lidar_m, dtype=float)
    T_map_lidar = np.matmul(T_map_vehicle, T_vehicle_lidar)
    R = T_map_lidar[:, :3, :3]
    A = R[:, :2, :2]  # d(east, north) / d(x_lidar, y_lidar) at z_lidar = 0
    en = np.einsum("nij,nj->ni", A, xy) + T_map_lidar[:, :2, 3]

    d = en - T_map_vehicle[:, :2, 3]
    n = len(xy)
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = 1.0
    J[:, 1, 1] = 1.0
    J[:, 0, 2] = -d[:, 1]
    J[:, 1, 2] = d[:, 0]
    cov_pose = J @ cov_pose_xy_yaw @ J.transpose(0, 2, 1)
    cov_corner = A @ cov_lidar_m2 @ A.transpose(0, 2, 1)

    theta = np.asarray(theta_lidar_rad, dtype=float)
    dirs = np.stack([np.cos(theta), np.sin(theta)], axis=-1)  # (N,2 walls,2 xy)
    dirs_en = np.einsum("nij,nkj->nki", A, dirs)
    theta_enu = canonicalize_pairs(np.arctan2(dirs_en[..., 1], dirs_en[..., 0]))
    sym = lambda m: 0.5 * (m + m.transpose(0, 2, 1))  # noqa: E731 - remove round-off asymmetry
    return EnuObservations(en, theta_enu, sym(cov_corner), sym(cov_pose), J,
                           sym(np.asarray(cov_pose_xy_yaw, float)))
