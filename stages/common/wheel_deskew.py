"""Motion compensation of one scan from wheel speed and yaw rate (shared by odometry and corners).

A spinning lidar takes ~0.1 s per revolution; at 10 m/s the vehicle moves 1 m meanwhile and, when turning,
walls are bent. Each point is moved from the lidar frame at its firing time into the lidar frame at the scan
start. Planar motion only (pitch/roll rates ignored); the vehicle moves along its x axis. The motion is either a
constant twist or the integral of odometry samples (speed and yaw rate at their own rate, e.g. 100 Hz), which
follows yaw-rate changes within the revolution.

Convention: ``T_vehicle_lidar`` maps lidar points into the vehicle frame (identity when the lidar sits on the
vehicle's reference point; the lever arm matters only through yaw_rate * lever * t, a few cm at most).
"""
from __future__ import annotations

import numpy as np

from stages.common.geometry import se3_from_xyz_rpy

_STEP_S = 0.001  # integration step of sampled odometry


def vehicle_motion_xy_yaw(time_s: np.ndarray, speed_mps: float, yaw_rate_radps: float) -> tuple[np.ndarray, ...]:
    """Pose of the vehicle at ``time_s`` in its pose at time 0 (constant speed and yaw rate): x, y, yaw."""
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


def deskew_points(points_xyz: np.ndarray, time_offset_s: np.ndarray, speed_mps, yaw_rate_radps,
                  T_vehicle_lidar: np.ndarray | None = None, *, odo_time_s: np.ndarray | None = None) -> np.ndarray:
    """Points (N, 3) in the lidar frame at their firing times -> the lidar frame at the scan start (float64).

    ``speed_mps`` / ``yaw_rate_radps``: scalars (constant twist), or arrays sampled at ``odo_time_s`` (seconds
    relative to the scan start; samples should cover the revolution).
    """
    p = np.asarray(points_xyz, np.float64)
    T = np.eye(4) if T_vehicle_lidar is None else np.asarray(T_vehicle_lidar, np.float64)
    R_vl, t_vl = T[:3, :3], T[:3, 3]
    pv = p @ R_vl.T + t_vl  # vehicle frame at the firing time
    if odo_time_s is None:
        x, y, yaw = vehicle_motion_xy_yaw(time_offset_s, float(speed_mps), float(yaw_rate_radps))
    else:
        x, y, yaw = integrate_odometry_xy_yaw(time_offset_s, odo_time_s, speed_mps, yaw_rate_radps)
    c, s = np.cos(yaw), np.sin(yaw)
    pv0 = np.column_stack([c * pv[:, 0] - s * pv[:, 1] + x, s * pv[:, 0] + c * pv[:, 1] + y, pv[:, 2]])
    return (pv0 - t_vl) @ R_vl  # back into the lidar frame at the scan start (R^T applied on the right)


class OdometryTrack:
    """Wheel speed [m/s] and yaw rate [rad/s] samples of one drive, sorted by time, looked up around any scan."""

    def __init__(self, stamp_ns: np.ndarray, speed_mps: np.ndarray, yaw_rate_radps: np.ndarray):
        order = np.argsort(np.asarray(stamp_ns), kind="stable")
        self.stamp_ns = np.asarray(stamp_ns)[order]
        self.speed_mps = np.asarray(speed_mps, np.float64)[order]
        self.yaw_rate_radps = np.asarray(yaw_rate_radps, np.float64)[order]

    @classmethod
    def from_table(cls, odometry) -> "OdometryTrack":
        """From an ``odometry_raw`` Arrow table (columns stamp_ns, speed_mps, yaw_rate_radps)."""
        return cls(odometry["stamp_ns"].to_numpy(), odometry["speed_mps"].to_numpy(),
                   odometry["yaw_rate_radps"].to_numpy())

    def covers(self, start_ns: int, duration_s: float, tolerance_s: float = 0.5) -> bool:
        """Whether the odometry spans the scan (within ``tolerance_s``); guards against a time-base mismatch."""
        tol = int(tolerance_s * 1e9)
        return bool(self.stamp_ns[0] - tol <= start_ns and start_ns + int(duration_s * 1e9) <= self.stamp_ns[-1] + tol)

    def around(self, start_ns: int, duration_s: float, margin_s: float = 0.05
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples (time relative to ``start_ns`` [s], speed, yaw rate) covering the scan; at least two, taken
        from the nearest samples (interpolated) when the odometry is sparser than the scan."""
        lo = np.searchsorted(self.stamp_ns, start_ns - int(margin_s * 1e9))
        hi = np.searchsorted(self.stamp_ns, start_ns + int((duration_s + margin_s) * 1e9), side="right")
        if hi - lo >= 2:
            sl = slice(lo, hi)
            return ((self.stamp_ns[sl] - start_ns) * 1e-9, self.speed_mps[sl], self.yaw_rate_radps[sl])
        t_rel = (self.stamp_ns - start_ns) * 1e-9
        q = np.array([0.0, duration_s])
        return q, np.interp(q, t_rel, self.speed_mps), np.interp(q, t_rel, self.yaw_rate_radps)

    def deskew_scan(self, points_xyz: np.ndarray, time_offset_s: np.ndarray, start_ns: int,
                    T_vehicle_lidar: np.ndarray | None = None) -> np.ndarray | None:
        """The scan's points in the lidar frame at its start, or None when the odometry does not cover it."""
        duration_s = float(np.max(time_offset_s)) if len(time_offset_s) else 0.0
        if not self.covers(start_ns, duration_s):
            return None
        odo_t, speed, yaw_rate = self.around(start_ns, duration_s)
        return deskew_points(points_xyz, time_offset_s, speed, yaw_rate, T_vehicle_lidar, odo_time_s=odo_t)


def track_from_table(odometry) -> OdometryTrack | None:
    """An ``OdometryTrack`` of one drive's odometry_raw rows, or None when there are fewer than two samples."""
    return OdometryTrack.from_table(odometry) if odometry.num_rows >= 2 else None


def wheel_increments(track: OdometryTrack | None, scan_ids: np.ndarray, stamps_ns: np.ndarray
                     ) -> dict[int, np.ndarray]:
    """scan_id -> planar vehicle increment T_prev_curr (4x4) from the previous scan, integrated from wheel speed
    and yaw rate, for every pair of consecutive scan ids that the odometry covers (``scan_ids`` sorted)."""
    out: dict[int, np.ndarray] = {}
    if track is None:
        return out
    for a, b, ta, tb in zip(scan_ids[:-1], scan_ids[1:], stamps_ns[:-1], stamps_ns[1:]):
        dt_s = (int(tb) - int(ta)) * 1e-9
        if b != a + 1 or dt_s <= 0 or not track.covers(int(ta), dt_s):
            continue
        odo_t, speed, yaw_rate = track.around(int(ta), dt_s)
        x, y, yaw = integrate_odometry_xy_yaw(np.array([dt_s]), odo_t, speed, yaw_rate)
        out[int(b)] = se3_from_xyz_rpy(x[0], y[0], 0.0, 0.0, 0.0, yaw[0])
    return out
