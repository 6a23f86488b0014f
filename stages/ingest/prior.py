"""A drive's prior trajectory (``prior:``) and stated start pose (``start:``) -> ``poses_prior`` rows.

The prior file (TUM or KITTI poses, ``stages.common.records.read_pose_file``) holds poses of the vehicle or the lidar
(``body``) in its frame: ``enu`` about a stated WGS84 origin (moved into the map's ENU frame by geodesy,
``trajectory_frame.move_poses``), or ``local`` (z up, origin and heading unknown: kept as it is, frame 'local').
With ``time: stamps`` its rows are interpolated to the scan stamps (linear position, SLERP attitude); a scan is
``valid`` when a row lies within ``EXACT_NS`` of its stamp or two rows no further apart than ``max_gap_s`` bracket
it. With ``time: scan_order`` row k is scan k. The std per axis is the drive file's.

The start pose is one row for the drive's first stamped scan, frame 'map_enu': at the map's origin (std 0) or at
the stated position, the stated heading, roll and pitch unknown (NaN std).

``as_absolute_poses``: until the pose graph reads ``poses_prior`` itself, a drive without GNSS takes these rows as
its ``poses_gnss`` (ingest param ``prior_as_gnss``): a prior in the map's frame as it is; a local prior aligned at
the start pose (a rotation about z and a shift), its horizontal std grown by the start's heading std times the
distance from the start and the start's position std (the frame's heading error turns the whole drive about its
start: at 1 deg, 17 m per km).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.errors import ConfigError
from stages.common.geodesy import EnuOrigin, geodetic_to_enu
from stages.common.geometry import se3_inverse
from stages.common.records import PriorPoses, read_pose_file
from stages.ingest.drive_file import DriveSpec
from stages.ingest.pose_interpolation import interpolate_poses

EXACT_NS = 1_000  # a prior row this close to a scan stamp is that scan's pose


def heading_to_yaw_rad(heading_deg: float, convention: str) -> float:
    yaw = np.radians(heading_deg) if convention == "enu_yaw_ccw_from_east" else np.pi / 2 - np.radians(heading_deg)
    return float((yaw + np.pi) % (2 * np.pi) - np.pi)


def prior_file_poses(spec: DriveSpec, drive: str, scan_ids: np.ndarray, scan_stamps_ns: np.ndarray,
                     origin: EnuOrigin | None, max_gap_s: float) -> PriorPoses:
    """The prior file's poses of the vehicle at the scans (``scan_ids`` sorted, their stamps)."""
    from stages.common.trajectory_frame import move_poses

    p = spec.prior
    rows = read_pose_file(spec.path(p.file), p.format, increasing=p.time == "stamps")
    T = rows.T
    if p.body == "lidar":  # T_frame_vehicle = T_frame_lidar @ T_lidar_vehicle
        T = T @ se3_inverse(spec.T_vehicle_lidar_matrix)
    frame = "local"
    if p.frame == "enu":
        if origin is None:
            raise ConfigError(f"drive {drive}", ["prior: frame enu needs the map's ENU origin (cornermap build "
                                                 "--origin, or a GNSS drive)"])
        T = move_poses(T, EnuOrigin(p.origin.lat_deg, p.origin.lon_deg, p.origin.h_m), origin)
        frame = "map_enu"
    n = len(scan_ids)
    if p.time == "scan_order":
        have = scan_ids < len(T)
        T_scan = np.tile(np.eye(4), (n, 1, 1))
        T_scan[have] = T[scan_ids[have]]
        valid = have
    else:
        stamps_ns = np.round(rows.stamp_s * 1e9).astype(np.int64)
        at = interpolate_poses(stamps_ns, T[:, :3, 3], Rotation.from_matrix(T[:, :3, :3]), np.zeros((len(T), 4)),
                               scan_stamps_ns, max_gap_s)
        T_scan = np.tile(np.eye(4), (n, 1, 1))
        T_scan[:, :3, :3] = Rotation.from_quat(at.quat_xyzw).as_matrix()
        T_scan[:, :3, 3] = at.position_enu_m
        nearest = np.abs(stamps_ns[np.clip(np.searchsorted(stamps_ns, scan_stamps_ns), 0, len(stamps_ns) - 1)]
                         - scan_stamps_ns)
        before = np.abs(stamps_ns[np.clip(np.searchsorted(stamps_ns, scan_stamps_ns) - 1, 0, len(stamps_ns) - 1)]
                        - scan_stamps_ns)
        inside = (scan_stamps_ns >= stamps_ns[0] - EXACT_NS) & (scan_stamps_ns <= stamps_ns[-1] + EXACT_NS)
        valid = inside & (at.valid | (np.minimum(nearest, before) <= EXACT_NS))
    std = np.tile(np.concatenate([p.std_m, np.radians(p.std_deg)]), (n, 1))
    return PriorPoses(drive, np.asarray(scan_ids, np.int64), np.asarray(scan_stamps_ns, np.int64), T_scan, std,
                      np.full(n, frame, dtype=object), np.full(n, "prior_file", dtype=object), np.asarray(valid, bool))


def start_pose(spec: DriveSpec, drive: str, scan_id: int, stamp_ns: int, origin: EnuOrigin | None) -> PriorPoses:
    """The stated start pose as one 'map_enu' row of the first scan."""
    s = spec.start
    if origin is None:
        raise ConfigError(f"drive {drive}", ["start: the drive starts at the map's origin, but the map has none; give "
                                             "cornermap build --origin LAT,LON,H (or start.position)"])
    if s.position is None:
        xyz, std_xyz = np.zeros(3), np.zeros(3)
    else:
        xyz = geodetic_to_enu(s.position.lat_deg, s.position.lon_deg, s.position.h_m, origin)[0]
        std_xyz = np.full(3, s.std_m)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", heading_to_yaw_rad(s.heading_deg, s.heading_convention)).as_matrix()
    T[:3, 3] = xyz
    std = np.concatenate([std_xyz, [np.nan, np.nan, np.radians(s.std_heading_deg)]])[None, :]
    return PriorPoses(drive, np.array([scan_id], np.int64), np.array([stamp_ns], np.int64), T[None], std,
                      np.array(["map_enu"], dtype=object), np.array(["start"], dtype=object), np.array([True]))


def concat(parts: list[PriorPoses], drive: str) -> PriorPoses:
    if not parts:
        return PriorPoses(drive, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6)),
                          np.zeros(0, dtype=object), np.zeros(0, dtype=object), np.zeros(0, bool))
    return PriorPoses(drive, *(np.concatenate([getattr(p, f) for p in parts]) for f in
                               ("scan_id", "stamp_ns", "T", "std", "frame", "source", "valid")))


@dataclass(frozen=True)
class AbsolutePoses:
    """Prior poses in the map's frame for ``poses_gnss`` (phase 1: the prior as the drive's absolute input)."""

    scan_id: np.ndarray
    stamp_ns: np.ndarray
    T: np.ndarray
    std_enu_yaw: np.ndarray  # (N,4): east, north, up m, yaw rad
    valid: np.ndarray
    how: str  # one line: what was taken and how it was aligned


def as_absolute_poses(prior: PriorPoses) -> AbsolutePoses | None:
    """The drive's poses in the map's frame from its prior (module docstring), or None when it has none: no prior
    rows, or a local prior without a start row at one of its valid scans."""
    from_file = prior.select(prior.source == "prior_file")
    start = prior.select(prior.source == "start")
    if not len(from_file.scan_id) or not from_file.valid.any():
        return None
    std = np.column_stack([from_file.std[:, 0], from_file.std[:, 1], from_file.std[:, 2], from_file.std[:, 5]])
    if from_file.frame[0] == "map_enu":
        return AbsolutePoses(from_file.scan_id, from_file.stamp_ns, from_file.T, std, from_file.valid,
                             "the prior trajectory (ENU, moved into the map's frame)")
    if not len(start.scan_id):
        return None
    at = np.flatnonzero((from_file.scan_id == start.scan_id[0]) & from_file.valid)
    if not len(at):
        return None
    T_local_first = from_file.T[at[0]]
    T_map_start = start.T[0]
    yaw_local = np.arctan2(T_local_first[1, 0], T_local_first[0, 0])
    yaw_map = np.arctan2(T_map_start[1, 0], T_map_start[0, 0])
    T_map_local = np.eye(4)
    T_map_local[:3, :3] = Rotation.from_euler("z", yaw_map - yaw_local).as_matrix()
    T_map_local[:3, 3] = T_map_start[:3, 3] - T_map_local[:3, :3] @ T_local_first[:3, 3]
    T = T_map_local @ from_file.T
    d_m = np.hypot(*(T[:, :2, 3] - T_map_start[:2, 3]).T)
    s = start.std[0]
    horizontal = np.sqrt(std[:, :2] ** 2 + s[0] ** 2 + (d_m * s[5])[:, None] ** 2)
    std_out = np.column_stack([horizontal, np.sqrt(std[:, 2] ** 2 + s[2] ** 2), np.hypot(std[:, 3], s[5])])
    return AbsolutePoses(from_file.scan_id, from_file.stamp_ns, T, std_out, from_file.valid,
                         f"the local prior trajectory aligned at the start pose (heading std "
                         f"{np.degrees(s[5]):.2f} deg: {1000 * s[5]:.1f} m per km from the start)")
