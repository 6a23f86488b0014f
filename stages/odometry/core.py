"""Odometry over a sequence of scans: initial guesses, deskewing, registration, vehicle-frame edges.

Arrays in, arrays out. ``T_vehicle_lidar`` maps lidar points into the vehicle frame; an edge is
``T_prev_curr`` of the vehicle frame with its 6x6 information (gtsam order, body frame of the edge).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.geometry import se3_inverse
from stages.odometry.icp import adjoint_se3, crop_range, deskew_points, prepare_cloud, register_clouds


@dataclass(frozen=True)
class Scan:
    scan_id: int
    stamp_ns: int
    points_lidar_m: np.ndarray  # (N,3)
    time_offset_s: np.ndarray | None  # (N,) or None when the scan carries no per-point time


@dataclass(frozen=True)
class Edge:
    scan_id: int  # the later scan; the earlier is scan_id - 1
    stamp_ns: int
    T_prev_curr: np.ndarray  # vehicle frame
    fitness: float
    inlier_rmse_m: float
    information: np.ndarray  # 6x6 gtsam order
    converged: bool


def lidar_to_vehicle_edge(T_lprev_lcurr: np.ndarray, information_lidar: np.ndarray,
                          T_vehicle_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move a lidar-frame relative pose and its body-frame information into the vehicle frame."""
    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    T_v = T_vehicle_lidar @ T_lprev_lcurr @ T_lidar_vehicle
    Ad = adjoint_se3(T_lidar_vehicle)  # xi_lidar = Ad(T_lidar_vehicle) xi_vehicle
    return T_v, Ad.T @ information_lidar @ Ad


def initial_guess(prev_pose_map: np.ndarray | None, curr_pose_map: np.ndarray | None,
                  last_edge: np.ndarray | None, dt_ratio: float) -> np.ndarray:
    """Vehicle increment guess: the GNSS/INS increment when both poses exist, else constant velocity."""
    if prev_pose_map is not None and curr_pose_map is not None:
        return se3_inverse(prev_pose_map) @ curr_pose_map
    if last_edge is None:
        return np.eye(4)
    return scale_motion(last_edge, dt_ratio)


def scale_motion(T: np.ndarray, ratio: float) -> np.ndarray:
    """Constant-velocity extrapolation of a small motion to ``ratio`` times its duration."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(ratio * Rotation.from_matrix(T[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = ratio * T[:3, 3]
    return out


def estimate_edges(scans: list[Scan], T_vehicle_lidar: np.ndarray, gnss_poses: dict[int, np.ndarray], *,
                   method: str, voxel_m: float, knn: int, max_corr_m: float, max_iterations: int,
                   relative_tolerance: float, min_range_m: float, max_range_m: float, deskew: bool,
                   min_fitness: float, max_deviation_m: float, point_sigma_m: float, min_sigma_m: float,
                   min_sigma_rad: float) -> list[Edge]:
    """Register each scan onto its predecessor (``scans`` sorted by id; pairs need consecutive ids).

    ``gnss_poses`` maps scan_id -> T_map_vehicle for scans with a valid GNSS/INS solution (initial guesses).
    Each scan is deskewed and prepared once, with the motion estimate available when it is the source.
    """
    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    edges: list[Edge] = []
    prev_cloud, prev_scan = None, None
    last_edge_v, last_dt_s = None, None
    for scan in scans:
        ok = crop_range(scan.points_lidar_m, min_range_m, max_range_m)
        pts = scan.points_lidar_m[ok]
        consecutive = prev_scan is not None and scan.scan_id == prev_scan.scan_id + 1
        dt_s = (scan.stamp_ns - prev_scan.stamp_ns) * 1e-9 if consecutive else None
        ratio = dt_s / last_dt_s if (dt_s and last_dt_s) else 1.0
        T_guess_v = initial_guess(gnss_poses.get(prev_scan.scan_id) if consecutive else None,
                                  gnss_poses.get(scan.scan_id), last_edge_v if consecutive else None, ratio)
        T_guess_l = T_lidar_vehicle @ T_guess_v @ T_vehicle_lidar
        if deskew and scan.time_offset_s is not None and dt_s:
            # motion over the sweep = the last ICP motion (constant velocity; GNSS increments carry
            # centimetres of white noise per scan, too much to deskew with); source at sweep start
            T_sweep_v = scale_motion(last_edge_v, ratio) if (consecutive and last_edge_v is not None) else T_guess_v
            pts = deskew_points(pts, scan.time_offset_s[ok], T_lidar_vehicle @ T_sweep_v @ T_vehicle_lidar, dt_s)
        cloud = prepare_cloud(pts, voxel_m, knn, with_covariances=(method == "gicp"))
        if consecutive and prev_cloud is not None:
            res = register_clouds(cloud, prev_cloud, T_guess_l, method=method, max_corr_m=max_corr_m,
                                  max_iterations=max_iterations, point_sigma_m=point_sigma_m,
                                  min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad,
                                  relative_tolerance=relative_tolerance)
            T_v, info_v = lidar_to_vehicle_edge(res.T_target_source, res.information, T_vehicle_lidar)
            deviation_m = float(np.linalg.norm(T_v[:3, 3] - T_guess_v[:3, 3]))
            gnss_guess = scan.scan_id in gnss_poses and prev_scan.scan_id in gnss_poses
            converged = res.converged and res.fitness >= min_fitness and (
                not gnss_guess or deviation_m <= max_deviation_m)
            edges.append(Edge(scan.scan_id, scan.stamp_ns, T_v, res.fitness, res.inlier_rmse_m, info_v,
                              converged))
            if converged:
                last_edge_v, last_dt_s = T_v, dt_s
        prev_cloud, prev_scan = cloud, scan
    return edges
