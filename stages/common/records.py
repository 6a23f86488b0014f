"""One codec per dataset shape: Arrow rows <-> small numpy records, used by every stage that reads them.

- Pose rows (``poses_gnss``, ``poses_odometry``, ``poses_optimized``: ``x_m, y_m, z_m, qx, qy, qz, qw``; and the
  relative ``dx_m, dy_m, dz_m`` + quaternion of ``odometry_edges``) <-> (N,4,4) homogeneous matrices:
  ``pose_matrices`` / ``pose_columns``, the heading alone with ``yaw_rad``; a drive's trajectory as ``Trajectory``,
  which also reads TUM trajectory files (``t x y z qx qy qz qw`` per line, t in seconds; simulator truth, references).
- ``drive_info.T_vehicle_lidar`` (16 floats, row-major 4x4; maps lidar points into the vehicle frame) <->
  ``Extrinsics`` (one matrix per drive), with a named error for a short or non-rigid row or a missing drive.

Quaternions are (x, y, z, w) (scipy's order). No algorithms here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from scipy.spatial.transform import Rotation

from pipeline.errors import FormatError

POSITION_COLUMNS = ("x_m", "y_m", "z_m")
INCREMENT_COLUMNS = ("dx_m", "dy_m", "dz_m")
QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw")


def _columns(table: pa.Table, names: tuple[str, ...], rows: np.ndarray | None) -> np.ndarray:
    out = np.column_stack([table[c].to_numpy() for c in names]).astype(float) if table.num_rows \
        else np.zeros((0, len(names)))
    return out if rows is None else out[rows]


def _matrices(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(N,3) positions and (N,4) quaternions -> (N,4,4) homogeneous poses; N may be 0."""
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    if len(xyz):
        T[:, :3, :3] = Rotation.from_quat(quat_xyzw).as_matrix()
        T[:, :3, 3] = xyz
    return T


def pose_matrices(table: pa.Table, rows: np.ndarray | None = None, *,
                  position: tuple[str, str, str] = POSITION_COLUMNS) -> np.ndarray:
    """(N,4,4) homogeneous poses from position + quaternion columns (``rows`` selects and orders; N may be 0)."""
    return _matrices(_columns(table, position, rows), _columns(table, QUATERNION_COLUMNS, rows))


def pose_columns(T: np.ndarray, *, position: tuple[str, str, str] = POSITION_COLUMNS) -> dict[str, np.ndarray]:
    """(N,4,4) poses -> the position and quaternion columns of a pose table (the inverse of ``pose_matrices``)."""
    T = np.asarray(T, float).reshape(-1, 4, 4)
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat() if len(T) else np.zeros((0, 4))
    cols = {name: T[:, k, 3] for k, name in enumerate(position)}
    cols.update({name: q[:, k] for k, name in enumerate(QUATERNION_COLUMNS)})
    return cols


def yaw_rad(table: pa.Table, rows: np.ndarray | None = None) -> np.ndarray:
    """(N,) heading (rotation about z of a ZYX Euler decomposition) of the quaternion columns."""
    q = _columns(table, QUATERNION_COLUMNS, rows)
    return Rotation.from_quat(q).as_euler("ZYX")[:, 0] if len(q) else np.zeros(0)


@dataclass(frozen=True)
class Trajectory:
    """One drive's poses, ordered by ``scan_id``: ``T[k]`` maps vehicle points of scan ``scan_id[k]`` (stamped
    ``stamp_ns[k]``) into the table's frame (ENU map for ``poses_*``)."""

    drive: str
    scan_id: np.ndarray
    stamp_ns: np.ndarray
    T: np.ndarray

    @classmethod
    def from_table(cls, table: pa.Table, drive: str) -> "Trajectory":
        """The rows of ``drive`` (all rows when the table has no ``drive`` column), sorted by scan_id."""
        if "drive" in table.column_names:
            table = table.filter(pc.equal(table["drive"], drive))
        table = table.sort_by("scan_id")
        return cls(drive, table["scan_id"].to_numpy(), table["stamp_ns"].to_numpy(), pose_matrices(table))

    @classmethod
    def from_tum(cls, path, drive: str = "") -> "Trajectory":
        """A TUM file (``t x y z qx qy qz qw`` per line, t in seconds, ``#`` comments): row k is scan k, stamped
        t rounded to the nanosecond; FormatError naming the file when a line does not hold 8 numbers."""
        try:
            rows = np.loadtxt(path, comments="#", ndmin=2)
        except ValueError as exc:
            raise FormatError(f"{path}: not a TUM trajectory (t x y z qx qy qz qw per line): {exc}") from exc
        if rows.shape[1] != 8:
            raise FormatError(f"{path}: a TUM trajectory has 8 columns (t x y z qx qy qz qw); got {rows.shape[1]}")
        return cls(drive, np.arange(len(rows), dtype=np.int64), np.round(rows[:, 0] * 1e9).astype(np.int64),
                   _matrices(rows[:, 1:4], rows[:, 4:8]))

    @property
    def stamp_s(self) -> np.ndarray:
        """``stamp_ns`` in seconds (float64: ~0.2 us steps at GPS-epoch magnitudes)."""
        return self.stamp_ns * 1e-9

    def to_columns(self) -> dict[str, np.ndarray | list]:
        """The columns ``drive, scan_id, stamp_ns, x_m, ..., qw`` (the pose-table fields every pose dataset has)."""
        return {"drive": [self.drive] * len(self.scan_id), "scan_id": self.scan_id, "stamp_ns": self.stamp_ns,
                **pose_columns(self.T)}

    @property
    def yaw_rad(self) -> np.ndarray:
        return np.arctan2(self.T[:, 1, 0], self.T[:, 0, 0])


@dataclass(frozen=True)
class Extrinsics:
    """``T_vehicle_lidar`` per drive, from ``drive_info`` rows."""

    T_vehicle_lidar: dict[str, np.ndarray]

    @classmethod
    def from_table(cls, drive_info: pa.Table) -> "Extrinsics":
        out = {}
        for drive, flat in zip(drive_info["drive"].to_pylist(), drive_info["T_vehicle_lidar"].to_pylist()):
            if flat is None or len(flat) != 16:
                raise FormatError(f"drive_info row of drive {drive!r}: T_vehicle_lidar must hold 16 values "
                                  f"(row-major 4x4), got {None if flat is None else len(flat)}")
            T = np.asarray(flat, float).reshape(4, 4)
            if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
                raise FormatError(f"drive_info row of drive {drive!r}: T_vehicle_lidar is not a rigid 4x4 transform; "
                                  f"got {T.tolist()}")
            out[drive] = T
        return cls(out)

    def of(self, drive: str) -> np.ndarray:
        """The drive's (4,4) T_vehicle_lidar; FormatError naming the drives present when it has no row."""
        if drive not in self.T_vehicle_lidar:
            raise FormatError(f"drive_info: no row for drive {drive!r} (rows for {sorted(self.T_vehicle_lidar)}); "
                              "hint: run ingest for this drive first")
        return self.T_vehicle_lidar[drive]

    @staticmethod
    def to_column(T_vehicle_lidar: np.ndarray) -> list[float]:
        """A (4,4) matrix as the ``T_vehicle_lidar`` cell of a drive_info row (16 floats, row-major)."""
        T = np.asarray(T_vehicle_lidar, float)
        if T.shape != (4, 4):
            raise FormatError(f"T_vehicle_lidar must be 4x4, got shape {T.shape}")
        return T.ravel().tolist()
