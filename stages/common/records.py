"""One codec per dataset shape: Arrow rows <-> small numpy records, used by every stage that reads them.

- Pose rows (``poses_gnss``, ``poses_odometry``, ``poses_optimized``: ``x_m, y_m, z_m, qx, qy, qz, qw``; and the
  relative ``dx_m, dy_m, dz_m`` + quaternion of ``odometry_edges``) <-> (N,4,4) homogeneous matrices:
  ``pose_matrices`` / ``pose_columns``, the heading alone with ``yaw_rad``; a drive's trajectory as ``Trajectory``,
  which also reads TUM trajectory files (``t x y z qx qy qz qw`` per line, t in seconds; simulator truth, references).
- Pose files a drive comes with (``read_pose_file``): TUM (``t x y z qx qy qz qw``) and KITTI odometry poses (12
  numbers, the top 3x4 of a pose, per line), each row with its file line, every malformed line a ``FormatError``
  naming file and line; ``poses_prior`` rows <-> ``PriorPoses``.
- ``drive_info.T_vehicle_lidar`` (16 floats, row-major 4x4; maps lidar points into the vehicle frame) <->
  ``Extrinsics`` (one matrix per drive), with a named error for a short or non-rigid row or a missing drive.
- ``scans_raw`` rows (one row per LiDAR point in the lidar frame, see schemas/raw.py) <-> ``RawScanPoints``:
  ``encode_scans_raw`` / ``decode_scans_raw``, points grouped by scan (``scan_rows``, ``rows_of``).

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
        t rounded to the nanosecond; FormatError naming the file and line when a line does not hold 8 numbers."""
        poses = read_pose_file(path, "tum")
        return cls(drive, np.arange(len(poses.T), dtype=np.int64), np.round(poses.stamp_s * 1e9).astype(np.int64),
                   poses.T)

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


POSE_FILE_COLUMNS = {"tum": 8, "kitti": 12}
MAX_POSE_FILE_BYTES = 256 << 20


@dataclass(frozen=True)
class PoseFile:
    """The rows of a TUM or KITTI poses file: ``T[k]`` maps body points into the file's frame."""

    stamp_s: np.ndarray | None  # (N,) TUM times; None for KITTI (row k is scan k)
    T: np.ndarray  # (N,4,4)
    line: np.ndarray  # (N,) 1-based file line of each row


def read_pose_file(path, fmt: str, *, increasing: bool = False) -> PoseFile:
    """A TUM (``t x y z qx qy qz qw``) or KITTI (``r00 r01 r02 tx r10 ... tz``) poses file; ``#`` comment and blank
    lines are skipped. FormatError naming the file and line for a line with another number of values, a value that
    is no finite number, a zero quaternion or a KITTI rotation that is not one (|R R^T - I| > 1e-3), and with
    ``increasing`` for a TUM time that does not increase."""
    from pathlib import Path

    path = Path(path)
    n_cols = POSE_FILE_COLUMNS[fmt]
    what = "t x y z qx qy qz qw" if fmt == "tum" else "12 numbers: the top 3x4 of a pose, row by row"
    try:
        if path.stat().st_size > MAX_POSE_FILE_BYTES:
            raise FormatError(f"{path}: more than {MAX_POSE_FILE_BYTES} bytes; not a poses file")
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not UTF-8 text (byte {exc.start}); expected a {fmt} poses file") from None
    except OSError as exc:
        from pipeline.errors import DatasetIOError

        raise DatasetIOError(f"{path}: cannot read poses: {exc.strerror or exc}") from exc
    rows, lines = [], []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != n_cols:
            raise FormatError(f"{path}: line {n}: {len(parts)} values; expected {n_cols} ({what})")
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise FormatError(f"{path}: line {n}: {line[:60]!r} holds a value that is not a number ({what})") from None
        if not np.all(np.isfinite(values)):
            raise FormatError(f"{path}: line {n}: a value is not finite ({what})")
        rows.append(values)
        lines.append(n)
    if not rows:
        raise FormatError(f"{path}: no pose line; expected {what} per line")
    a = np.asarray(rows, float)
    if fmt == "tum":
        norm = np.linalg.norm(a[:, 4:8], axis=1)
        if np.any(norm < 1e-9):
            raise FormatError(f"{path}: line {lines[int(np.argmin(norm))]}: zero quaternion (qx qy qz qw)")
        if increasing and len(a) > 1 and np.any(np.diff(a[:, 0]) <= 0):
            k = int(np.flatnonzero(np.diff(a[:, 0]) <= 0)[0]) + 1
            raise FormatError(f"{path}: line {lines[k]}: time {float(a[k, 0])!r} does not increase (previous "
                              f"{float(a[k - 1, 0])!r})")
        return PoseFile(a[:, 0], _matrices(a[:, 1:4], a[:, 4:8] / norm[:, None]), np.asarray(lines))
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :4] = a.reshape(-1, 3, 4)
    err = np.abs(T[:, :3, :3] @ np.transpose(T[:, :3, :3], (0, 2, 1)) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(T[:, :3, :3])
    bad = (err > 1e-3) | (det < 0)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise FormatError(f"{path}: line {lines[k]}: the 3x3 part is not a rotation (|R R^T - I| = {err[k]:.2g}, det "
                          f"{det[k]:.3f}); expected {what}")
    return PoseFile(None, T, np.asarray(lines))


PRIOR_STD_COLUMNS = ("std_x_m", "std_y_m", "std_z_m", "std_roll_rad", "std_pitch_rad", "std_yaw_rad")


@dataclass(frozen=True)
class PriorPoses:
    """One drive's ``poses_prior`` rows (see schemas/raw.py): ``T[k]`` maps vehicle points of ``scan_id[k]`` into
    ``frame[k]`` ('map_enu': the map's ENU frame; 'local': the prior file's own z-up frame, origin and heading
    unknown), with a std per axis (NaN: no information on that axis) and where it comes from ('prior_file',
    'start')."""

    drive: str
    scan_id: np.ndarray
    stamp_ns: np.ndarray
    T: np.ndarray
    std: np.ndarray  # (N,6): x y z m, roll pitch yaw rad
    frame: np.ndarray  # (N,) str
    source: np.ndarray  # (N,) str
    valid: np.ndarray  # (N,) bool

    @classmethod
    def from_table(cls, table: pa.Table, drive: str) -> "PriorPoses":
        if "drive" in table.column_names:
            table = table.filter(pc.equal(table["drive"], drive))
        table = table.sort_by([("source", "ascending"), ("scan_id", "ascending")])
        std = _columns(table, PRIOR_STD_COLUMNS, None)
        return cls(drive, table["scan_id"].to_numpy(), table["stamp_ns"].to_numpy(), pose_matrices(table), std,
                   np.asarray(table["frame"].to_pylist(), dtype=object),
                   np.asarray(table["source"].to_pylist(), dtype=object),
                   table["valid"].to_numpy(zero_copy_only=False).astype(bool))

    def to_columns(self) -> dict:
        n = len(self.scan_id)
        return {"drive": [self.drive] * n, "scan_id": np.asarray(self.scan_id, np.int64),
                "stamp_ns": np.asarray(self.stamp_ns, np.int64), **pose_columns(self.T),
                **{c: np.asarray(self.std, float).reshape(n, 6)[:, k] for k, c in enumerate(PRIOR_STD_COLUMNS)},
                "frame": [str(f) for f in self.frame], "source": [str(s) for s in self.source],
                "valid": np.asarray(self.valid, bool)}

    def select(self, mask: np.ndarray) -> "PriorPoses":
        return PriorPoses(self.drive, self.scan_id[mask], self.stamp_ns[mask], self.T[mask], self.std[mask],
                          self.frame[mask], self.source[mask], self.valid[mask])


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


SCANS_RAW_POINT_COLUMNS = ("x_m", "y_m", "z_m", "intensity", "ring", "time_offset_s")
_XYZ = ("x_m", "y_m", "z_m")


@dataclass(frozen=True)
class RawScanPoints:
    """``scans_raw`` rows as per-point arrays in their stored dtypes (points float32): point ``k`` belongs to scan
    ``scan_id[k]``, started at ``stamp_ns[k]``, lies at ``xyz_lidar_m[k]`` in the lidar frame and was measured
    ``time_offset_s[k]`` after the scan start by laser ``ring[k]``. A column that was not read is None. Decoded
    with ``by_scan`` the rows are grouped by scan (a stable sort by scan_id): ``scan_rows`` gives each scan's rows.
    """

    scan_id: np.ndarray  # (N,) int64
    stamp_ns: np.ndarray | None = None  # (N,) int64, the scan's start
    xyz_lidar_m: np.ndarray | None = None  # (N,3)
    intensity: np.ndarray | None = None  # (N,)
    ring: np.ndarray | None = None  # (N,)
    time_offset_s: np.ndarray | None = None  # (N,)

    def __len__(self) -> int:
        return len(self.scan_id)

    def scan_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(S,) scan ids in row order and (S+1,) row bounds: scan ``ids[k]`` is rows ``bounds[k]:bounds[k+1]``
        (rows grouped by scan, as ``decode_scans_raw(by_scan=True)`` gives them)."""
        sid = self.scan_id
        if sid.size == 0:
            return np.zeros(0, np.int64), np.zeros(1, np.int64)
        starts = np.r_[0, np.flatnonzero(sid[1:] != sid[:-1]) + 1]
        return sid[starts], np.r_[starts, sid.size]

    def rows_of(self, scan_ids) -> list[slice]:
        """The row slice of each of ``scan_ids`` (empty for a scan without rows); rows sorted by scan_id."""
        wanted = np.asarray(scan_ids, np.int64)
        lo = np.searchsorted(self.scan_id, wanted, "left")
        hi = np.searchsorted(self.scan_id, wanted, "right")
        return [slice(int(a), int(b)) for a, b in zip(lo, hi)]


def encode_scans_raw(drive: str, chunk: int, points: RawScanPoints) -> pa.Table:
    """``scans_raw`` rows of one drive's chunk; every point column is required (``time_offset_s`` None: zeros)."""
    from schemas import SCHEMAS

    n = len(points)
    for name in ("stamp_ns", "xyz_lidar_m", "intensity", "ring"):
        value = getattr(points, name)
        if value is None or len(value) != n:
            raise FormatError(f"scans_raw of drive {drive!r} chunk {chunk}: {name} must hold {n} rows (one per "
                              f"point), got {None if value is None else len(value)}")
    xyz = np.asarray(points.xyz_lidar_m).reshape(n, 3)
    t_s = points.time_offset_s if points.time_offset_s is not None else np.zeros(n, np.float32)
    return pa.table({
        "drive": pa.repeat(pa.scalar(drive, pa.string()), n),
        "chunk": np.full(n, chunk, np.int32),
        "scan_id": np.asarray(points.scan_id).astype(np.int64, copy=False),
        "stamp_ns": np.asarray(points.stamp_ns).astype(np.int64, copy=False),
        **{c: np.ascontiguousarray(xyz[:, j], np.float32) for j, c in enumerate(_XYZ)},
        "intensity": np.asarray(points.intensity).astype(np.float32, copy=False),
        "ring": np.asarray(points.ring).astype(np.int16, copy=False),
        "time_offset_s": np.asarray(t_s).astype(np.float32, copy=False),
    }, schema=SCHEMAS["scans_raw"])


def decode_scans_raw(table: "pa.Table | pa.RecordBatch", *, by_scan: bool = True) -> RawScanPoints:
    """``scans_raw`` rows (any subset of columns holding ``scan_id``, or ``x_m, y_m, z_m`` all three or none) ->
    ``RawScanPoints``. ``by_scan``: rows grouped by scan (stable sort by scan_id when they are not already in scan
    order, as ingest writes them); otherwise in the table's order (``scan_id`` may then be absent: zeros).
    FormatError naming the column for a partial point triple, and naming the scan when the rows of one scan carry
    different ``stamp_ns``."""
    names = set(table.schema.names)
    if by_scan and "scan_id" not in names:
        raise FormatError(f"scans_raw rows: no scan_id column (columns {sorted(names)}); expected scan_id to group "
                          "points by scan")
    missing = [c for c in _XYZ if c not in names]
    if missing and len(missing) < 3:
        raise FormatError(f"scans_raw rows: {', '.join(missing)} missing next to the other point coordinates; "
                          "expected x_m, y_m, z_m together")
    sid = (table.column("scan_id").to_numpy() if "scan_id" in names else np.zeros(table.num_rows, np.int64))
    order = None
    if by_scan and sid.size and np.any(sid[1:] < sid[:-1]):
        order = np.argsort(sid, kind="stable")
        sid = sid[order]

    def col(name: str) -> np.ndarray | None:
        if name not in names:
            return None
        a = table.column(name).to_numpy()
        return a if order is None else a[order]

    xyz = None if missing else np.column_stack([col(c) for c in _XYZ])
    out = RawScanPoints(sid, col("stamp_ns"), xyz, col("intensity"), col("ring"), col("time_offset_s"))
    if by_scan and out.stamp_ns is not None and sid.size:
        bad = np.flatnonzero((sid[1:] == sid[:-1]) & (out.stamp_ns[1:] != out.stamp_ns[:-1]))
        if bad.size:
            k = int(bad[0]) + 1
            raise FormatError(f"scans_raw rows of scan {int(sid[k])}: stamp_ns {int(out.stamp_ns[k])} and "
                              f"{int(out.stamp_ns[k - 1])}; expected one scan start per scan")
    return out
