"""GNSS/INS poses -> vehicle poses at scan stamps: lever arm, linear position, SLERP attitude, gap flags.

Attitude is Rz(yaw) Ry(pitch) Rx(roll) (``stages.common.geometry`` convention), yaw ENU counter-clockwise
from east. SLERP interpolates the shortest arc, so yaw wraps (+pi -> -pi) need no special handling.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


@dataclass(frozen=True)
class InterpolatedPoses:
    position_enu_m: np.ndarray  # (M, 3) vehicle origin in ENU
    quat_xyzw: np.ndarray  # (M, 4) T_map_vehicle rotation
    std: np.ndarray  # (M, 4) std east, north, up (m), yaw (rad)
    valid: np.ndarray  # (M,) bool: bracketed by fixes no further apart than the gap threshold


def attitude_from_rpy(roll_rad: np.ndarray, pitch_rad: np.ndarray, yaw_rad: np.ndarray) -> Rotation:
    return Rotation.from_euler("ZYX", np.column_stack([yaw_rad, pitch_rad, roll_rad]))


def vehicle_origin_from_reference(reference_enu_m: np.ndarray, R_map_vehicle: Rotation,
                                  lever_arm_m: np.ndarray) -> np.ndarray:
    """The GNSS/INS solution is at ``lever_arm_m`` (vehicle frame): p_vehicle = p_ref - R_map_vehicle @ lever."""
    return np.asarray(reference_enu_m, float) - R_map_vehicle.apply(np.asarray(lever_arm_m, float))


def interpolate_poses(stamp_ns: np.ndarray, position_enu_m: np.ndarray, attitude: Rotation, std: np.ndarray,
                      query_ns: np.ndarray, max_gap_s: float) -> InterpolatedPoses:
    """Interpolate strictly increasing fixes to ``query_ns``. Queries outside the fixes or inside a gap longer
    than ``max_gap_s`` get the nearest / interpolated value with ``valid=False``."""
    stamp_ns = np.asarray(stamp_ns, np.int64)
    query_ns = np.asarray(query_ns, np.int64)
    m = len(query_ns)
    n = len(stamp_ns)
    if n == 0:
        nan = np.full((m, 3), np.nan)
        return InterpolatedPoses(nan, np.tile([0.0, 0.0, 0.0, 1.0], (m, 1)), np.full((m, 4), np.nan),
                                 np.zeros(m, bool))
    if n == 1:
        return InterpolatedPoses(np.repeat(position_enu_m[:1], m, 0), np.repeat(attitude[:1].as_quat(), m, 0),
                                 np.repeat(std[:1], m, 0), query_ns == stamp_ns[0])
    i0 = np.clip(np.searchsorted(stamp_ns, query_ns, side="right") - 1, 0, n - 2)
    i1 = i0 + 1
    span_ns = stamp_ns[i1] - stamp_ns[i0]
    frac = np.clip((query_ns - stamp_ns[i0]) / span_ns.astype(np.float64), 0.0, 1.0)
    position = position_enu_m[i0] + frac[:, None] * (position_enu_m[i1] - position_enu_m[i0])
    std_q = std[i0] + frac[:, None] * (std[i1] - std[i0])
    t_rel_s = (stamp_ns - stamp_ns[0]) / 1e9
    q_rel_s = np.clip((query_ns - stamp_ns[0]) / 1e9, 0.0, t_rel_s[-1])
    quat = Slerp(t_rel_s, attitude)(q_rel_s).as_quat()
    inside = (query_ns >= stamp_ns[0]) & (query_ns <= stamp_ns[-1])
    valid = inside & (span_ns <= round(max_gap_s * 1e9))
    return InterpolatedPoses(position, quat, std_q, valid)
