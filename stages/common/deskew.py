"""Motion compensation (deskew) of one lidar sweep: one kernel, two sources of the sweep's motion.

A spinning lidar takes ~0.1 s per revolution; at 10 m/s the vehicle moves 1 m meanwhile and, when turning,
walls are bent. Each point is moved from the sensor frame at its firing time into the sensor frame at the sweep
start: ``p_start = R_k p_k + t_k`` with ``(R_k, t_k)`` the sensor pose at the point's time offset in the
sensor frame at the start (a ``SweepMotion``). ``deskew_points`` is that kernel; the motion comes from

- ``motion_from_transform``: a start->end transform over the sweep period (registration, pose-graph increments),
  at constant velocity with rotation (on SO(3), rotation vector scaled) and translation (scaled) interpolated
  separately. For a planar turn this places the sensor on the chord, not the arc: off the true constant-twist
  path by at most the sagitta ``L * theta / 8`` (L the sweep's distance, theta its yaw; 3.75 mm at 10 m/s and
  0.3 rad/s over 0.1 s), tested against ``motion_from_wheel`` in tests/stages/common/test_deskew.py;
- ``motion_from_wheel``: the planar arc of wheel speed and yaw rate, either a constant twist (scalars) or the
  integral of odometry samples (arrays at their own rate, e.g. 100 Hz), which follows yaw-rate changes within
  the revolution. Planar motion only (pitch/roll rates ignored); the vehicle moves along its x axis.
  ``T_vehicle_lidar`` maps lidar points into the vehicle frame (the lever arm matters through
  yaw_rate * lever * t, a few cm at most).

Pure numpy; ``T_a_b`` maps points of frame b into frame a.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from stages.common.geometry import skew

_STEP_S = 0.001  # integration step of sampled odometry


@dataclass(frozen=True)
class SweepMotion:
    """Per point k, the sensor pose at its firing time in the sensor frame at the sweep start (T_start_k)."""

    R: np.ndarray  # (N,3,3)
    t_m: np.ndarray  # (N,3)


def deskew_points(points_m: np.ndarray, motion: SweepMotion) -> np.ndarray:
    """Points (N,3) in the sensor frame at their firing times -> the sensor frame at the sweep start (float64)."""
    p = np.asarray(points_m, np.float64)[:, :3]
    return np.einsum("nij,nj->ni", motion.R, p) + motion.t_m


def interpolate_transform(T_start_end: np.ndarray, fraction: np.ndarray) -> SweepMotion:
    """The poses at ``fraction`` (N,) of a constant-velocity motion ``T_start_end``: rotation vector and
    translation both scaled by the fraction (any fraction; > 1 extrapolates)."""
    s = np.asarray(fraction, np.float64).reshape(-1)
    rotvec = Rotation.from_matrix(T_start_end[:3, :3]).as_rotvec()
    R = Rotation.from_rotvec(s[:, None] * rotvec[None, :]).as_matrix().reshape(-1, 3, 3)
    return SweepMotion(R, s[:, None] * np.asarray(T_start_end, np.float64)[:3, 3][None, :])


def _sweep_fraction(time_offset_s: np.ndarray, period_s: float) -> np.ndarray:
    """(N,) share of the sweep's motion at each point's time: ``t / period_s`` clipped to [-1, 2]."""
    return np.clip(np.asarray(time_offset_s, np.float64).reshape(-1) / period_s, -1.0, 2.0)


def motion_from_transform(time_offset_s: np.ndarray, T_start_end: np.ndarray, period_s: float) -> SweepMotion:
    """Motion source 1: ``T_start_end`` is the sensor motion over ``period_s``; a point taken ``t`` seconds after
    the start gets the fraction ``t / period_s`` of it (clipped to [-1, 2])."""
    return interpolate_transform(T_start_end, _sweep_fraction(time_offset_s, period_s))


def vehicle_motion_xy_yaw(time_s: np.ndarray, speed_mps: float, yaw_rate_radps: float) -> tuple[np.ndarray, ...]:
    """Pose of the vehicle at ``time_s`` in its pose at time 0 (constant speed and yaw rate: an arc): x, y, yaw."""
    t = np.asarray(time_s, np.float64)
    yaw = yaw_rate_radps * t
    if abs(yaw_rate_radps) < 1e-9:
        return speed_mps * t, np.zeros_like(t), yaw
    radius = speed_mps / yaw_rate_radps
    return radius * np.sin(yaw), radius * (1.0 - np.cos(yaw)), yaw


def integrate_odometry_xy_yaw(time_s: np.ndarray, odo_time_s: np.ndarray, speed_mps: np.ndarray,
                              yaw_rate_radps: np.ndarray) -> tuple[np.ndarray, ...]:
    """Pose of the vehicle at ``time_s`` in its pose at time 0, integrating sampled speed and yaw rate
    (``odo_time_s`` relative to the same time 0, increasing; linear interpolation between samples)."""
    t = np.asarray(time_s, np.float64)
    if np.size(odo_time_s) == 0:
        raise ValueError("integrate_odometry_xy_yaw: no odometry samples; hint: pass samples around the scan or "
                         "scalar speed and yaw rate")
    t_max = max(float(t.max(initial=0.0)), 0.0)
    grid = np.arange(0.0, t_max + 2 * _STEP_S, _STEP_S)
    v = np.interp(grid, odo_time_s, speed_mps)
    w = np.interp(grid, odo_time_s, yaw_rate_radps)
    yaw = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * _STEP_S)]
    mid_yaw = 0.5 * (yaw[1:] + yaw[:-1])
    step = 0.5 * (v[1:] + v[:-1]) * _STEP_S
    x = np.r_[0.0, np.cumsum(step * np.cos(mid_yaw))]
    y = np.r_[0.0, np.cumsum(step * np.sin(mid_yaw))]
    return np.interp(t, grid, x), np.interp(t, grid, y), np.interp(t, grid, yaw)


def _wheel_xy_yaw(time_offset_s: np.ndarray, speed_mps, yaw_rate_radps, odo_time_s: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vehicle's planar pose (x, y, yaw; each (N,)) at each point's time in its pose at the sweep start: the arc
    of a constant twist (scalars) or the integral of sampled odometry (arrays at ``odo_time_s``)."""
    if odo_time_s is None:
        x, y, yaw = vehicle_motion_xy_yaw(time_offset_s, float(speed_mps), float(yaw_rate_radps))
    else:
        x, y, yaw = integrate_odometry_xy_yaw(time_offset_s, odo_time_s, speed_mps, yaw_rate_radps)
    return tuple(np.asarray(a, np.float64).reshape(-1) for a in (x, y, yaw))


def motion_from_wheel(time_offset_s: np.ndarray, speed_mps, yaw_rate_radps,
                      T_vehicle_lidar: np.ndarray | None = None, *, odo_time_s: np.ndarray | None = None
                      ) -> SweepMotion:
    """Motion source 2, in the lidar frame: the vehicle's planar motion (``vehicle_motion_xy_yaw`` for scalar
    ``speed_mps`` / ``yaw_rate_radps``, ``integrate_odometry_xy_yaw`` for arrays sampled at ``odo_time_s``,
    seconds relative to the sweep start) seen through ``T_vehicle_lidar`` (identity when None)."""
    T = np.eye(4) if T_vehicle_lidar is None else np.asarray(T_vehicle_lidar, np.float64)
    R_vl, t_vl = T[:3, :3], T[:3, 3]
    x, y, yaw = _wheel_xy_yaw(time_offset_s, speed_mps, yaw_rate_radps, odo_time_s)
    c, s = np.cos(yaw), np.sin(yaw)
    R_v = np.zeros((len(yaw), 3, 3))
    R_v[:, 0, 0], R_v[:, 0, 1], R_v[:, 1, 0], R_v[:, 1, 1], R_v[:, 2, 2] = c, -s, s, c, 1.0
    t_v = np.column_stack([x, y, np.zeros_like(x)])
    # T_lidar0_lidark = T_lidar_vehicle T_vehicle0_vehiclek T_vehicle_lidar
    R = R_vl.T @ R_v @ R_vl
    t_m = (R_v @ t_vl + t_v - t_vl) @ R_vl
    return SweepMotion(R, t_m)


def deskew_with_transform(points_m: np.ndarray, time_offset_s: np.ndarray, T_start_end: np.ndarray,
                          period_s: float) -> np.ndarray:
    """``deskew_points`` with ``motion_from_transform``; the points unchanged (float64) for an empty scan or a
    non-positive period."""
    if period_s <= 0 or len(points_m) == 0:
        return np.asarray(points_m, dtype=float)
    s = _sweep_fraction(time_offset_s, period_s)
    p = np.asarray(points_m, np.float64)[:, :3]
    T = np.asarray(T_start_end, np.float64)
    return rotate_about_axis(p, Rotation.from_matrix(T[:3, :3]).as_rotvec(), s) + s[:, None] * T[:3, 3][None, :]


def rotate_about_axis(points_m: np.ndarray, rotvec: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Each point (N,3) turned by its ``fraction`` (N,) of the rotation vector ``rotvec`` (Rodrigues' formula,
    without an (N,3,3) matrix per point; equal to ``deskew_points(p, interpolate_transform(...))`` to 1e-9 m,
    tests/stages/common/test_deskew.py)."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-15:
        return points_m.copy()
    K = skew(np.asarray(rotvec, np.float64) / theta)  # k x p = K p; k (k . p) - p = K K p
    angle = fraction * theta
    # p + sin(a) K p + (1 - cos(a)) K K p, the cross and outer products as two (N,3)@(3,3) products: 2.95 -> 1.70 ms
    # a 40k-point sweep against np.cross / np.outer per point, equal to 7e-15 m
    out = points_m @ K.T
    out *= np.sin(angle)[:, None]
    out += (points_m @ (K @ K).T) * (1.0 - np.cos(angle))[:, None]
    out += points_m
    return out


def deskew_with_wheel(points_m: np.ndarray, time_offset_s: np.ndarray, speed_mps, yaw_rate_radps,
                      T_vehicle_lidar: np.ndarray | None = None, *, odo_time_s: np.ndarray | None = None
                      ) -> np.ndarray:
    """``deskew_points`` with ``motion_from_wheel`` (the same arguments), applied point by point without an (N,3,3)
    rotation per point: into the vehicle frame, turned by the yaw and moved by the planar travel at the point's
    time, back into the lidar frame (equal to the ``SweepMotion`` form to 1e-9 m; that form took a third of an
    odometry task's time). Only the vehicle-frame x and y move, so the lidar-frame shift is that planar shift through
    the extrinsic's first two rows: 1.40 -> 1.22 ms a 40k-point sweep against the round trip through the vehicle
    frame, equal to 3e-14 m."""
    x, y, yaw = _wheel_xy_yaw(time_offset_s, speed_mps, yaw_rate_radps, odo_time_s)
    T = np.eye(4) if T_vehicle_lidar is None else np.asarray(T_vehicle_lidar, np.float64)
    p = np.asarray(points_m, np.float64)[:, :3]
    # the planar motion moves a point's vehicle-frame x and y only: out = p + R^T [dx, dy, 0], R^T's first two columns
    # being R's first two rows; q: the point's vehicle-frame x, y at its firing time
    q = p @ T[:2, :3].T + T[:2, 3]
    c1, s = np.cos(yaw) - 1.0, np.sin(yaw)
    d = np.empty_like(q)
    d[:, 0] = c1 * q[:, 0] - s * q[:, 1] + x
    d[:, 1] = s * q[:, 0] + c1 * q[:, 1] + y
    return p + d @ T[:2, :3]  # vehicle frame at the sweep start -> lidar frame at the sweep start
