"""A version's trajectories (``trajectories/{drive}.tum``) read back, and exported as TUM or KITTI files that
state their frame.

Exports (``cornermap tiles export -f tum|kitti -o DIR``), one set per source drive of the version:

- ``DIR/{drive}.tum``: ``t x y z qx qy qz qw`` (``T_map_vehicle``, map ENU; ``t`` seconds of the drive's time base,
  printed exactly from the integer nanosecond stamps) after ``#`` comment lines: the frame line of
  ``stages.common.trajectory_frame`` (ENU origin, WGS84), the attitude (``3-D``: the pose graph's roll, pitch and
  yaw) and the time base. evo's TUM reader and numpy skip ``#`` lines.
- ``DIR/{drive}.kitti.txt``: the top 3 x 4 of each ``T_map_vehicle``, row-major, 12 numbers a line (KITTI has no
  header and no stamps); ``DIR/{drive}.times.txt``: the stamp of each line (s, same base as the TUM file);
  ``DIR/{drive}.kitti.frame.json``: frame, origin, rows, attitude, time base, map and version (the sidecar
  ``stages.common.trajectory_frame.read_trajectory_origin`` reads).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from pipeline.errors import MapFormatError
from stages.common.geodesy import EnuOrigin
from stages.common.trajectory_frame import attitude_header, frame_header, sidecar_path, sidecar_text

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

TIME_BASE = "t: seconds of the drive's time base (GPS time for simulated drives), exact from integer ns"


def parse_tum_stamps_ns(tokens: list[str]) -> np.ndarray:
    """TUM stamps as written by the tiles stage ("SEC.NNNNNNNNN") -> int64 ns, exactly."""
    out = np.empty(len(tokens), np.int64)
    for k, tok in enumerate(tokens):
        sec, _, frac = tok.partition(".")
        out[k] = int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])
    return out


def read_version_trajectory(reader: "MapReader", drive: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamp_ns (N,), pose_xyz_qxyzw (N, 7)) of ``drive`` from the version's ``trajectories/`` file."""
    entry = next((d for d in reader.manifest.get("source_drives", []) if d.get("drive") == drive), None)
    if entry is None or not entry.get("trajectory"):
        raise MapFormatError(f"{reader.path}: no trajectory of drive {drive!r} in the manifest's source_drives")
    import hashlib

    from pipeline.names import inside

    path = inside(reader.path, entry["trajectory"])
    try:
        raw = path.read_bytes()
        want = ((reader.manifest.get("files") or {}).get(entry["trajectory"]) or {}).get("sha256")
        if want is not None and hashlib.sha256(raw).hexdigest() != want:
            raise ValueError("its sha256 differs from the manifest's")
        rows = [ln.split() for ln in raw.decode("utf-8").splitlines() if ln and not ln.startswith("#")]
        poses = np.array([[float(v) for v in r[1:8]] for r in rows], float).reshape(-1, 7)
        stamps = parse_tum_stamps_ns([r[0] for r in rows])
    except (OSError, ValueError, IndexError, UnicodeDecodeError) as exc:
        raise MapFormatError(f"{path}: unreadable trajectory ({exc}); hint: run `cornermap tiles verify`") from exc
    return stamps, poses


def poses_matrices(pose_xyz_qxyzw: np.ndarray) -> np.ndarray:
    """(N, 7) x y z qx qy qz qw -> (N, 4, 4)."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(pose_xyz_qxyzw, float).reshape(-1, 7)
    T = np.tile(np.eye(4), (len(p), 1, 1))
    if len(p):
        T[:, :3, :3] = Rotation.from_quat(p[:, 3:7]).as_matrix()
        T[:, :3, 3] = p[:, :3]
    return T


def format_stamps_s(stamp_ns: np.ndarray) -> list[str]:
    sec, frac = np.divmod(np.asarray(stamp_ns, np.int64), 1_000_000_000)
    return [f"{s}.{f:09d}" for s, f in zip(sec.tolist(), frac.tolist())]


def tum_text(stamp_ns: np.ndarray, T: np.ndarray, header: list[str]) -> str:
    """TUM rows after ``#`` header lines; quaternions from the rotation matrices (scipy), w >= 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:, :3, :3]).as_quat() if len(T) else np.zeros((0, 4))
    q = np.where(q[:, 3:4] < 0, -q, q)
    rows = [f"{t} {x:.6f} {y:.6f} {z:.6f} {a:.9f} {b:.9f} {c:.9f} {d:.9f}" for t, (x, y, z), (a, b, c, d)
            in zip(format_stamps_s(stamp_ns), T[:, :3, 3].tolist(), q.tolist())]
    return "".join(f"# {h}\n" for h in header) + "".join(r + "\n" for r in rows)


def kitti_text(T: np.ndarray) -> str:
    """KITTI rows: the top 3 x 4 of each pose, row-major, 12 numbers a line."""
    return "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in T[:, :3, :4].reshape(len(T), 12).tolist())


def export_trajectories(reader: "MapReader", fmt: str, out: Path, write: Callable[[Path, bytes], None]) -> list[Path]:
    """Every source drive's trajectory of the version as ``fmt`` (``tum`` | ``kitti``) files under ``out``."""
    from mapformat.layout import trajectory_file_name

    origin = EnuOrigin.from_dict(reader.manifest["enu_origin"])
    where = f"map {reader.manifest.get('map_name')!r} v{reader.version:04d}"
    files = []
    for entry in sorted(reader.manifest.get("source_drives", []), key=lambda d: d["drive"]):
        drive = entry["drive"]
        stamps, poses = read_version_trajectory(reader, drive)
        T = poses_matrices(poses)
        stem = Path(trajectory_file_name(drive)).stem
        attitude = attitude_header(planar=False)
        if fmt == "tum":
            path = Path(out) / f"{stem}.tum"
            write(path, tum_text(stamps, T, [f"cornermap trajectory of drive {drive!r}, {where}",
                                             frame_header(origin), attitude, TIME_BASE]).encode("utf-8"))
            files.append(path)
            continue
        path = Path(out) / f"{stem}.kitti.txt"
        write(path, kitti_text(T).encode("utf-8"))
        times = Path(out) / f"{stem}.times.txt"
        write(times, "".join(t + "\n" for t in format_stamps_s(stamps)).encode("utf-8"))
        side = sidecar_path(path)
        write(side, sidecar_text(origin, rows="T_enu_vehicle: top 3x4 of each pose, row-major (KITTI)",
                                 attitude="3-D (x y z, roll pitch yaw as estimated)",
                                 times=f"{times.name}: one stamp per line, {TIME_BASE[3:]}", drive=drive,
                                 map=reader.manifest.get("map_name"), version=reader.version,
                                 n_poses=int(len(T))).encode("utf-8"))
        files += [path, times, side]
    return files
