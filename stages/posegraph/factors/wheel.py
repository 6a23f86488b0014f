"""Wheel odometry in the graph: the per-drive scale and gyro-bias calibration against the accepted ICP edges,
and the noise of a (planar) wheel increment."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stages.posegraph.config import WheelNoise

if TYPE_CHECKING:
    from stages.posegraph.factors.drive import DriveInput


@dataclass(frozen=True)
class WheelCalibration:
    scale: float  # true distance / wheel distance
    yaw_rate_bias_radps: float  # true yaw rate - measured yaw rate
    n_edges: int  # ICP edges it was estimated from (0: identity calibration)


def calibrate_wheel(drive: DriveInput, min_step_m: float = 0.2, max_mismatch: float = 0.05,
                    min_edges: int = 50) -> WheelCalibration:
    """Wheel scale and gyro bias of one drive against its accepted ICP edges (robust medians over pairs where
    both exist, the vehicle moves ``min_step_m`` and the two agree within ``max_mismatch`` of the step).
    A bridge of 30 m on a 1 % scale error is 0.3 m off otherwise (measured: gangnam drive 0 -1.2 %)."""
    if drive.wheel_ok is None:
        return WheelCalibration(1.0, 0.0, 0)
    k = np.flatnonzero(drive.edge_ok & drive.wheel_ok)
    k = k[k > 0]
    wx, ix = drive.wheel_T[k, 0, 3], drive.edge_T[k, 0, 3]
    ok = (np.abs(wx) > min_step_m) & (np.abs(ix - wx) < max_mismatch * np.abs(wx))
    if ok.sum() < min_edges:
        return WheelCalibration(1.0, 0.0, int(ok.sum()))
    k, wx, ix = k[ok], wx[ok], ix[ok]
    dt_s = (drive.stamps_ns[k] - drive.stamps_ns[k - 1]) * 1e-9
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
    bias = np.median((yaw(drive.edge_T[k]) - yaw(drive.wheel_T[k])) / dt_s)
    return WheelCalibration(float(np.median(ix / wx)), float(bias), int(len(k)))


def calibrated_wheel_increments(drive: DriveInput, cal: WheelCalibration) -> np.ndarray:
    """(N,4,4) wheel increments with the drive's scale and gyro bias applied (planar)."""
    W = drive.wheel_T.copy()
    dt_s = np.diff(drive.stamps_ns, prepend=drive.stamps_ns[0]) * 1e-9
    dyaw = cal.yaw_rate_bias_radps * dt_s
    c, s = np.cos(dyaw), np.sin(dyaw)
    R = W[:, :2, :2].copy()
    W[:, :2, :2] = np.einsum("nij,njk->nik", R, np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2))
    W[:, :2, 3] *= cal.scale
    return W


def wheel_information(T_prev_curr: np.ndarray, noise: WheelNoise) -> np.ndarray:
    """6x6 information (gtsam order rx ry rz tx ty tz) of a planar wheel increment."""
    along_m = noise.sigma_m + noise.scale_sigma * abs(float(T_prev_curr[0, 3]))
    sig = [noise.tilt_sigma_rad, noise.tilt_sigma_rad, noise.sigma_rad, along_m, noise.sigma_m,
           noise.height_sigma_m]
    return np.diag(np.asarray(sig) ** -2.0)
