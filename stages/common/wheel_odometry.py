"""One drive's wheel odometry (speed and yaw rate samples, ``odometry_raw``): the samples around a scan, the
scan deskewed with them (``stages.common.deskew``), planar increments between scans.

``T_vehicle_lidar`` maps lidar points into the vehicle frame.
"""
from __future__ import annotations

import numpy as np

from stages.common.deskew import deskew_with_wheel, integrate_odometry_xy_yaw
from stages.common.geometry import se3_from_xyz_rpy


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
        return deskew_with_wheel(points_xyz, time_offset_s, speed, yaw_rate, T_vehicle_lidar, odo_time_s=odo_t)


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
