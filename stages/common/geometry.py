"""Rigid-body helpers shared by stages (pure numpy, float64).

Convention, stated once: ``T_a_b`` is a 4x4 (or 3x3 for SE(2)) homogeneous matrix that maps points expressed
in frame b into frame a: ``p_a = T_a_b @ p_b``. Yaw is ENU, counter-clockwise from east, radians.
Quaternions are (qx, qy, qz, qw), as in the TUM trajectory format.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def wrap_angle_rad(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def se2_matrix(x: float, y: float, yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_params(T: np.ndarray) -> tuple[float, float, float]:
    return float(T[0, 2]), float(T[1, 2]), float(np.arctan2(T[1, 0], T[0, 0]))


def se3_matrix(translation: np.ndarray, rotation: Rotation | np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation)
    T[:3, 3] = np.asarray(translation, dtype=float)
    return T


def se3_from_xyz_rpy(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation = Rz(yaw) Ry(pitch) Rx(roll) (intrinsic z-y'-x'', the usual vehicle convention)."""
    return se3_matrix([x, y, z], Rotation.from_euler("ZYX", [yaw, pitch, roll]))


def se3_to_xyz_rpy(T: np.ndarray) -> np.ndarray:
    yaw, pitch, roll = Rotation.from_matrix(T[:3, :3]).as_euler("ZYX")
    return np.array([T[0, 3], T[1, 3], T[2, 3], roll, pitch, yaw])


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 cross-product matrix: skew(a) @ b = a x b."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def se3_inverse(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 (N,3 points) or 3x3 (N,2 points) homogeneous transform."""
    d = T.shape[0] - 1
    return points[:, :d] @ T[:d, :d].T + T[:d, d]


def poses_to_tum_rows(stamps_s: np.ndarray, T_world_body: np.ndarray) -> np.ndarray:
    """(N,4,4) poses -> (N,8) rows t x y z qx qy qz qw."""
    q = Rotation.from_matrix(T_world_body[:, :3, :3]).as_quat()  # x y z w
    return np.column_stack([stamps_s, T_world_body[:, :3, 3], q])


def write_tum(path, stamps_s: np.ndarray, T_world_body: np.ndarray, header: str = "") -> None:
    """Write a TUM trajectory (t x y z qx qy qz qw), atomically; ``header`` lines become '# ' comments."""
    import os
    from pathlib import Path

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    np.savetxt(tmp, poses_to_tum_rows(stamps_s, T_world_body), fmt="%.9f", header=header, comments="# ")
    os.replace(tmp, path)


def write_kitti(path, T_world_body: np.ndarray) -> None:
    """KITTI odometry format: 12 numbers per line, the top 3x4 of each pose."""
    import os
    from pathlib import Path

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    np.savetxt(tmp, T_world_body[:, :3, :4].reshape(len(T_world_body), 12), fmt="%.9e")
    os.replace(tmp, path)


def fit_rigid_2d(src_m: np.ndarray, dst_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R (2x2) and translation t with ``dst ~ src @ R.T + t`` (Kabsch, no scale)."""
    src, dst = np.asarray(src_m, dtype=float), np.asarray(dst_m, dtype=float)
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs
