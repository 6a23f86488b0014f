"""Scan sources of the odometry bench: the real KITTI scans and a simulated drive (files, stamps, extrinsics,
wheel track), read as the odometry's ``Scan`` records."""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
KITTI_DEFAULT = REPO.parent / "shared" / "data" / "kitti_raw_0048_city"
KITTI_LIDAR_HEIGHT_M = 1.73  # KITTI's Velodyne above the ground; vehicle frame on the ground below it
CHUNK_SCANS = 100  # the ingest stage's default chunk; chunk c re-reads the last scan of chunk c-1


@dataclass(frozen=True)
class ScanFile:
    scan_id: int
    stamp_ns: int
    path: Path


def kitti_files(folder: Path) -> list[ScanFile]:
    paths = sorted(folder.glob("*.pcd"))
    if not paths:
        raise FileNotFoundError(f"{folder}: no *.pcd scans; hint: pass --kitti DIR")
    return [ScanFile(i, i * 100_000_000, p) for i, p in enumerate(paths)]  # KITTI raw: 10 Hz


def kitti_extrinsic() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = KITTI_LIDAR_HEIGHT_M
    return T


def _gps_ns(week: str, seconds: str) -> int:
    whole, _, frac = seconds.partition(".")
    return (int(week) * 604800 + int(whole)) * 1_000_000_000 + int((frac + "000000000")[:9])


def sim_files(sim: Path, drive: str, n_max: int | None) -> list[ScanFile]:
    with open(sim / drive / "scans" / "stamps.csv") as fh:
        rows = list(csv.DictReader(fh))
    files = [ScanFile(int(r["scan_id"]), _gps_ns(r["gps_week"], r["gps_seconds"]),
                      sim / drive / "scans" / f"{int(r['scan_id']):06d}.pcd") for r in rows]
    return files[:n_max] if n_max else files


def sim_extrinsic(sim: Path) -> np.ndarray:
    return np.asarray(json.loads((sim / "simulation.json").read_text())["T_vehicle_lidar"], dtype=float)


def sim_track(sim: Path, drive: str):
    from stages.common.wheel_odometry import OdometryTrack

    with open(sim / drive / "wheel_gyro.csv") as fh:
        rows = list(csv.DictReader(fh))
    return OdometryTrack(np.array([_gps_ns(r["gps_week"], r["gps_seconds"]) for r in rows], dtype=np.int64),
                         np.array([float(r["wheel_speed_mps"]) for r in rows]),
                         np.array([float(r["yaw_rate_radps"]) for r in rows]))


def read_scan(f: ScanFile):
    from stages.ingest.pcd import read_pcd
    from stages.odometry.core import Scan

    cols = read_pcd(f.path).columns
    xyz = np.column_stack([cols[c].astype(np.float64) for c in ("x", "y", "z")])
    keep = np.any(xyz != 0, axis=1) & np.all(np.isfinite(xyz), axis=1)  # KITTI's trailing (0,0,0) record
    t = cols["time"].astype(np.float64)[keep] if "time" in cols else None
    return Scan(f.scan_id, f.stamp_ns, xyz[keep], t if t is not None and np.any(t != 0) else None)


def chunked(files: list[ScanFile], size: int) -> Iterator[list]:
    for a in range(0, len(files), size):
        yield [read_scan(f) for f in files[a:a + size]]
