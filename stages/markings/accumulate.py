"""A mobile-mapping cloud from the drives' own scans: lidar points -> ENU map points with optimized poses.

Used when no survey cloud is given. Pure numpy. ``T_map_vehicle`` comes from ``poses_optimized`` (one per
scan, at the scan's start), ``T_vehicle_lidar`` from ``drive_info``; a point p_lidar of scan s lands at
``T_map_vehicle[s] @ T_vehicle_lidar @ p_lidar``, or, given the points' time offsets in the sweep and the poses'
stamps, at ``T_map_vehicle[s] @ D(f) @ T_vehicle_lidar @ p_lidar``: ``D`` the vehicle's motion from scan s to the
next scan (its optimized pose; the previous step where there is none), interpolated on SE(3) at the point's share
``f`` of that step (rotation about the step's axis, translation linear). A sweep lasts 0.1 s: at 10 m/s and 29 deg/s
(a city turn) its last points sit 1 m and 2.9 deg from where the scan-start pose puts them, 1 m across a line 20 m
away.
"""
from __future__ import annotations

import numpy as np


def _rotate_about(v: np.ndarray, axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """(N,3) vectors rotated about a unit ``axis`` by (N,) angles (Rodrigues)."""
    c, s = np.cos(angle_rad)[:, None], np.sin(angle_rad)[:, None]
    return v * c + np.cross(axis, v) * s + np.outer(v @ axis, axis) * (1.0 - c)


def sweep_motion(T_map_vehicle: np.ndarray, stamps_ns: np.ndarray, scan_ids: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per pose (sorted by scan id): the vehicle's motion over the next scan step in its own frame (4x4; the
    previous step where the next scan has no pose) and that step's duration in seconds (0: no motion known)."""
    n = len(scan_ids)
    D = np.tile(np.eye(4), (n, 1, 1))
    dt = np.zeros(n)
    if n < 2:
        return D, dt
    step = (np.diff(scan_ids) == 1) & (np.diff(stamps_ns) > 0)
    has_next, has_prev = np.r_[step, False], np.r_[False, step]
    k = np.flatnonzero(has_next)
    D[k] = np.linalg.inv(T_map_vehicle[k]) @ T_map_vehicle[k + 1]
    dt[k] = np.diff(stamps_ns)[k] * 1e-9
    last = np.flatnonzero(~has_next & has_prev)  # the scan before a gap (or the last): its previous step
    D[last], dt[last] = D[last - 1], dt[last - 1]
    return D, dt


def scans_to_enu(points_lidar_m: np.ndarray, point_scan_ids: np.ndarray, pose_scan_ids: np.ndarray,
                 T_map_vehicle: np.ndarray, T_vehicle_lidar: np.ndarray, *, min_range_m: float = 2.5,
                 max_range_m: float = 25.0, time_offset_s: np.ndarray | None = None,
                 pose_stamps_ns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Transform lidar points into the map; returns ((K,3) ENU points, (N,) bool mask of the kept points).

    Kept: points whose scan has a pose and whose horizontal range in the lidar frame is within
    [min_range_m, max_range_m] (drops the ego vehicle and sparse far returns). With ``time_offset_s`` (N,) and
    ``pose_stamps_ns`` each point is placed at its own time in the sweep (module docstring).
    """
    pts = np.asarray(points_lidar_m, float).reshape(-1, 3)
    scan_ids = np.asarray(point_scan_ids, np.int64)
    order = np.argsort(pose_scan_ids, kind="stable")
    sorted_ids = np.asarray(pose_scan_ids, np.int64)[order]
    if sorted_ids.size == 0:
        return np.empty((0, 3)), np.zeros(len(pts), bool)
    pos = np.clip(np.searchsorted(sorted_ids, scan_ids), 0, sorted_ids.size - 1)
    has_pose = sorted_ids[pos] == scan_ids
    range_m = np.hypot(pts[:, 0], pts[:, 1])
    keep = has_pose & (range_m >= min_range_m) & (range_m <= max_range_m) & np.isfinite(pts).all(axis=1)
    T_sorted = np.asarray(T_map_vehicle, float)[order]
    T_vl = np.asarray(T_vehicle_lidar, float)
    T_map_lidar = T_sorted @ T_vl
    deskew = time_offset_s is not None and pose_stamps_ns is not None
    if deskew:
        D, dt = sweep_motion(T_sorted, np.asarray(pose_stamps_ns, np.int64)[order], sorted_ids)
        t_kept = np.asarray(time_offset_s, float)[keep]
    which = pos[keep]
    kept = pts[keep]
    enu = np.empty((len(kept), 3))
    # One rotation per scan, not per point: an (N,3,3) gather of 12 M points is 0.9 GB (measured on KITTI).
    boundaries = np.flatnonzero(np.diff(which)) + 1
    for start, stop in zip(np.r_[0, boundaries], np.r_[boundaries, len(which)]):
        s = which[start]
        if not deskew or dt[s] <= 0:
            T = T_map_lidar[s]
            enu[start:stop] = kept[start:stop] @ T[:3, :3].T + T[:3, 3]
            continue
        q = kept[start:stop] @ T_vl[:3, :3].T + T_vl[:3, 3]  # vehicle frame, at the point's own time
        f = t_kept[start:stop] / dt[s]
        rotvec = _rotvec(D[s, :3, :3])
        angle = float(np.linalg.norm(rotvec))
        if angle > 1e-12:
            q = _rotate_about(q, rotvec / angle, f * angle)
        q = q + f[:, None] * D[s, :3, 3]
        enu[start:stop] = q @ T_sorted[s, :3, :3].T + T_sorted[s, :3, 3]
    return enu, keep


def _rotvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle) of a 3x3 rotation (angles well under pi: one scan's turn)."""
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * (angle / (2.0 * np.sin(angle)))
