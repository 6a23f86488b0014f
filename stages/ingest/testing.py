"""A small synthetic drive on disk with known truth, for tests and the bench (not used by the stage)."""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.ingest.pcd import write_pcd
from stages.ingest.sensors import SENSORS

GPS_WEEK = 2200


@dataclass(frozen=True)
class SyntheticDrive:
    drive_file: Path
    origin: EnuOrigin
    scan_stamps_ns: np.ndarray
    gnss_stamps_ns: np.ndarray
    vehicle_xyz_enu_m: np.ndarray  # (G, 3) vehicle origin at each GNSS stamp
    yaw_enu_rad: np.ndarray  # (G,)
    lever_arm_m: tuple[float, float, float]
    scans: list[dict]  # per scan: the columns written to its PCD


def vehicle_truth(t_s: np.ndarray, speed_mps: float = 8.0, yaw_rate_radps: float = 0.05) -> tuple:
    """Constant speed and yaw rate from the ENU origin heading east: an exact circle arc."""
    yaw = yaw_rate_radps * t_s
    x = speed_mps / yaw_rate_radps * np.sin(yaw)
    y = speed_mps / yaw_rate_radps * (1 - np.cos(yaw))
    return np.column_stack([x, y, np.full_like(t_s, 1.5)]), yaw


def make_scan(rng: np.random.Generator, n_per_ring: int = 100, sensor: str = "hdl32e") -> dict:
    table = np.asarray(SENSORS[sensor].elevations_deg)
    ring = np.repeat(np.arange(len(table)), n_per_ring).astype(np.uint16)
    az = np.tile(np.linspace(-np.pi, np.pi, n_per_ring, endpoint=False), len(table))
    rng_m = rng.uniform(3.0, 60.0, ring.size)
    elev = np.radians(table[ring])
    return {"x": (rng_m * np.cos(elev) * np.cos(az)).astype(np.float32),
            "y": (rng_m * np.cos(elev) * np.sin(az)).astype(np.float32),
            "z": (rng_m * np.sin(elev)).astype(np.float32),
            "intensity": rng.uniform(0, 255, ring.size).astype(np.float32), "ring": ring,
            "time": ((az + np.pi) / (2 * np.pi) * 0.1).astype(np.float32)}


def write_synthetic_drive(root: Path, name: str = "drive_0", n_scans: int = 6, seed: int = 0,
                          encoding: str = "binary", lever_arm_m=(0.5, -0.2, 1.0), n_per_ring: int = 100,
                          origin: EnuOrigin = EnuOrigin(37.5665, 126.9780, 38.0)) -> SyntheticDrive:
    rng = np.random.default_rng(seed)
    drive_dir = Path(root) / name
    (drive_dir / "scans").mkdir(parents=True, exist_ok=True)
    t0_s = 345_600.0  # seconds of week
    scan_t = t0_s + 0.05 + np.arange(n_scans) * 0.1
    scans = []
    for i in range(n_scans):
        cols = make_scan(rng, n_per_ring)
        write_pcd(drive_dir / "scans" / f"{i:06d}.pcd", cols, encoding)
        scans.append(cols)
    with open(drive_dir / "scans" / "stamps.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scan_id", "gps_seconds", "gps_week"])
        w.writerows([i, f"{t:.9f}", GPS_WEEK] for i, t in enumerate(scan_t))
    gnss_t = t0_s + np.arange(int(n_scans * 0.1 / 0.01) + 10) * 0.01
    xyz, yaw = vehicle_truth(gnss_t - t0_s)
    R_lever = np.column_stack([np.cos(yaw), np.sin(yaw)])  # level vehicle: rotate the lever arm by yaw
    lever = np.asarray(lever_arm_m, float)
    ref = xyz + np.column_stack([R_lever[:, 0] * lever[0] - R_lever[:, 1] * lever[1],
                                 R_lever[:, 1] * lever[0] + R_lever[:, 0] * lever[1], np.full(len(yaw), lever[2])])
    geo = enu_to_geodetic(ref, origin)
    with open(drive_dir / "gnss_inspva.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["gps_week", "gps_seconds", "latitude_deg", "longitude_deg", "height_m", "roll_deg",
                    "pitch_deg", "azimuth_deg", "std_lat_m", "std_lon_m", "std_height_m", "std_azimuth_deg"])
        for k in range(len(gnss_t)):
            w.writerow([GPS_WEEK, f"{gnss_t[k]:.9f}", f"{geo[k, 0]:.12f}", f"{geo[k, 1]:.12f}", f"{geo[k, 2]:.6f}",
                        0.0, 0.0, f"{(90.0 - np.degrees(yaw[k])) % 360.0:.9f}", 0.02, 0.03, 0.05, 0.1])
    with open(drive_dir / "wheel_gyro.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["gps_seconds", "wheel_speed_mps", "yaw_rate_radps"])
        w.writerows([f"{t:.6f}", 8.0, 0.05] for t in gnss_t)
    spec = {
        "name": name, "sensor": "hdl32e", "scans": {"folder": "scans", "format": "pcd"}, "scan_rate_hz": 10.0,
        "T_vehicle_lidar": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.9], [0, 0, 0, 1]],
        "gnss": {"file": "gnss_inspva.csv", "time": {"column": "gps_seconds", "week_column": "gps_week",
                                                     "base": "gps"},
                 "columns": {"lat": "latitude_deg", "lon": "longitude_deg", "height": "height_m",
                             "roll": "roll_deg", "pitch": "pitch_deg", "heading": "azimuth_deg",
                             "std_east": "std_lon_m", "std_north": "std_lat_m", "std_up": "std_height_m",
                             "std_heading": "std_azimuth_deg"},
                 "angle_unit": "deg", "heading_convention": "azimuth_cw_from_north",
                 "lever_arm_m": list(lever_arm_m)},
        "odometry": {"file": "wheel_gyro.csv", "time_column": "gps_seconds", "speed": "wheel_speed_mps",
                     "yaw_rate": "yaw_rate_radps"},
        "scan_times": {"source": "pcd_field"},
    }
    drive_file = drive_dir / "drive.yaml"
    drive_file.write_text(yaml.safe_dump(spec, sort_keys=False))
    week_ns = GPS_WEEK * 604_800 * 1_000_000_000
    return SyntheticDrive(drive_file, origin, week_ns + np.round(scan_t * 1e9).astype(np.int64),
                          week_ns + np.round(gnss_t * 1e9).astype(np.int64), xyz, yaw, tuple(lever_arm_m), scans)
