"""Per-drive inputs of the pose graph: increments (ICP where accepted, else bridged), dead reckoning, initial
values, a scan's own-sweep deskew. Arrays in, arrays out; ``T_map_vehicle`` poses in the workflow's ENU frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stages.common.deskew import deskew_with_transform
from stages.common.geometry import se3_inverse

if TYPE_CHECKING:
    from stages.common.records import PriorPoses
    from stages.posegraph.factors.wheel import WheelCalibration


@dataclass
class DriveInput:
    """One drive: a row per scan (from poses_gnss) and the ICP edge into each scan where one exists."""

    name: str
    scan_ids: np.ndarray  # (N,) sorted
    stamps_ns: np.ndarray  # (N,)
    gnss_T: np.ndarray  # (N,4,4) T_map_vehicle from GNSS/INS (meaningless where not valid)
    gnss_std_enu_m: np.ndarray  # (N,3)
    gnss_std_yaw_rad: np.ndarray  # (N,)
    gnss_valid: np.ndarray  # (N,) bool
    edge_T: np.ndarray  # (N,4,4) T_prev_curr into scan k (identity where none)
    edge_info: np.ndarray  # (N,6,6)
    edge_ok: np.ndarray  # (N,) bool: an ICP edge from scan k-1 into scan k exists and was accepted
    T_vehicle_lidar: np.ndarray  # (4,4)
    wheel_T: np.ndarray | None = None  # (N,4,4) planar wheel-odometry increment into scan k (where wheel_ok)
    wheel_ok: np.ndarray | None = None  # (N,) bool
    wheel_calibration: WheelCalibration | None = None  # applied to wheel_T (report)
    spans: SpanEdges | None = None  # odometry span edges (scans N apart), accepted ones only
    gnss_roll_pitch_known: np.ndarray | None = None  # (N,) bool; None: all known
    prior: PriorPoses | None = None  # the drive's poses_prior rows (prior trajectory, start pose)
    prior_T: np.ndarray | None = None  # (N,4,4) T_map_vehicle from the prior where prior_known (factors.prior)
    prior_known: np.ndarray | None = None  # (N,) bool

    @property
    def n(self) -> int:
        return len(self.scan_ids)


@dataclass(frozen=True)
class SpanEdges:
    """ICP edges between scans N apart (odometry ``span_scans``): positions in the drive, T_from_to, information."""

    i: np.ndarray  # (M,) position of the earlier scan
    j: np.ndarray  # (M,) position of the later scan
    T_i_j: np.ndarray  # (M,4,4) vehicle frame
    information: np.ndarray  # (M,6,6) gtsam order


def absolute_poses(drive: DriveInput) -> tuple[np.ndarray, np.ndarray]:
    """(N,4,4) T_map_vehicle and (N,) valid: the GNSS/INS poses; for a drive without any valid fix, its prior's
    (``factors.prior.prior_in_map``: a prior trajectory, or the start pose alone)."""
    if drive.gnss_valid.any() or drive.prior_known is None:
        return drive.gnss_T, drive.gnss_valid
    return drive.prior_T, drive.prior_known


def has_wheel(drive: DriveInput, k: int) -> bool:
    return drive.wheel_ok is not None and bool(drive.wheel_ok[k])


def bridge_increment(drive: DriveInput, k: int) -> np.ndarray:
    """Relative pose k-1 -> k when ICP gave none: the wheel-odometry increment, else the GNSS/INS increment (the
    prior's without GNSS), else the neighbouring edge."""
    if has_wheel(drive, k):
        return drive.wheel_T[k]
    T_abs, valid = absolute_poses(drive)
    if valid[k] and valid[k - 1]:
        return se3_inverse(T_abs[k - 1]) @ T_abs[k]
    ok = np.flatnonzero(drive.edge_ok)
    if len(ok) == 0:
        return np.eye(4)
    return drive.edge_T[ok[np.argmin(np.abs(ok - k))]]


def increments(drive: DriveInput) -> np.ndarray:
    """(N,4,4) T_prev_curr for every scan (index 0 is the identity): ICP where accepted, else bridged."""
    inc = np.tile(np.eye(4), (drive.n, 1, 1))
    for k in range(1, drive.n):
        inc[k] = drive.edge_T[k] if drive.edge_ok[k] else bridge_increment(drive, k)
    return inc


def deskew_scan_lidar(drive: DriveInput, increments_drive: np.ndarray | None, k: int, points_lidar_m: np.ndarray,
                      time_offset_s: np.ndarray | None) -> np.ndarray:
    """Scan k's lidar points compensated for its own sweep (the motion into scan k+1, in the lidar frame);
    unchanged when the scan has no per-point times or is the drive's last."""
    if time_offset_s is None or k + 1 >= drive.n:
        return points_lidar_m
    T_l = se3_inverse(drive.T_vehicle_lidar) @ increments_drive[k + 1] @ drive.T_vehicle_lidar
    period_s = (drive.stamps_ns[k + 1] - drive.stamps_ns[k]) * 1e-9
    return deskew_with_transform(points_lidar_m, time_offset_s, T_l, period_s)


def chain(start: np.ndarray, inc: np.ndarray) -> np.ndarray:
    out = np.empty_like(inc)
    out[0] = start
    for k in range(1, len(inc)):
        out[k] = out[k - 1] @ inc[k]
    return out


def dead_reckoning(drive: DriveInput) -> np.ndarray:
    """ICP-only poses, started at the first valid GNSS/INS pose (without GNSS: the prior's; identity if the drive
    has neither)."""
    inc = increments(drive)
    T_abs, known = absolute_poses(drive)
    valid = np.flatnonzero(known)
    if len(valid) == 0:
        return chain(np.eye(4), inc)
    k0 = valid[0]
    T = chain(np.eye(4), inc)
    return T_abs[k0] @ se3_inverse(T[k0]) @ T


def initial_poses(drive: DriveInput) -> np.ndarray:
    """GNSS/INS pose where valid (without GNSS: the prior's); through outages, odometry from the last valid
    pose."""
    inc = increments(drive)
    out = np.empty_like(inc)
    dr = dead_reckoning(drive)
    T_abs, known = absolute_poses(drive)
    for k in range(drive.n):
        if known[k]:
            out[k] = T_abs[k]
        else:
            out[k] = out[k - 1] @ inc[k] if k > 0 else dr[0]
    return out
