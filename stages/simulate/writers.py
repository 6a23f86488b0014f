"""File writers for the simulation (the I/O edge): PCD binary scans, INSPVA-style GNSS CSV, wheel/gyro CSV,
LAS 1.4 survey with its CRS, drive.yaml and the ground-truth files. Nothing time-dependent is written, so
the same (preset, seed) gives byte-identical files.
"""
from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError

PCD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
                      ("time", "<f4")])


def write_pcd(path: Path, pts: dict[str, np.ndarray]) -> None:
    """PCD v0.7 binary with fields x y z intensity ring time (ring uint16, others float32)."""
    n = len(pts["x"])
    rec = np.empty(n, PCD_DTYPE)
    for name in PCD_DTYPE.names:
        rec[name] = pts[name]
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity ring time\n"
              "SIZE 4 4 4 4 2 4\nTYPE F F F F U F\nCOUNT 1 1 1 1 1 1\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    try:
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(rec.tobytes())
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot write scan ({exc}); hint: check free disk space") from exc


def write_csv(path: Path, header: list[str], columns: list[np.ndarray], fmts: list[str]) -> None:
    """A CSV with one fixed printf format per column (deterministic text)."""
    lines = [",".join(header)]
    cols = [np.asarray(c) for c in columns]
    fmt = ",".join(fmts)
    lines += [fmt % row for row in zip(*cols)]
    path.write_text("\n".join(lines) + "\n")


def write_gnss_csv(path: Path, week: int, gps_s: np.ndarray, llh: np.ndarray, roll_deg: np.ndarray | None,
                   pitch_deg: np.ndarray | None, azimuth_deg: np.ndarray, std_enu_m: np.ndarray,
                   std_azimuth_deg: np.ndarray, status: str = "INS_SOLUTION_GOOD") -> None:
    """INSPVA-like CSV; ``roll_deg`` / ``pitch_deg`` None: no such columns (a receiver without an INS)."""
    header = ["gps_week", "gps_seconds", "latitude_deg", "longitude_deg", "height_m", "roll_deg", "pitch_deg",
              "azimuth_deg", "std_lat_m", "std_lon_m", "std_height_m", "std_azimuth_deg", "status"]
    n = len(gps_s)
    cols = [np.full(n, week), gps_s, llh[:, 0], llh[:, 1], llh[:, 2], roll_deg, pitch_deg, azimuth_deg,
            std_enu_m[:, 1], std_enu_m[:, 0], std_enu_m[:, 2], std_azimuth_deg, np.full(n, status)]
    fmts = ["%d", "%.3f", "%.10f", "%.10f", "%.4f", "%.5f", "%.5f", "%.5f", "%.4f", "%.4f", "%.4f", "%.4f", "%s"]
    keep = [k for k, c in enumerate(cols) if c is not None]
    write_csv(path, [header[k] for k in keep], [cols[k] for k in keep], [fmts[k] for k in keep])


def write_drive_yaml(path: Path, name: str, T_vehicle_lidar: np.ndarray, survey_crs: str | None,
                     survey_dir: str = "survey", *, sensor: str = "hdl32e", gnss_attitude: bool = True,
                     gnss: bool = True, start: dict | None = None, prior: dict | None = None) -> None:
    """The drive file; ``survey_crs`` None: no survey section; ``gnss_attitude`` False: the GNSS file has no roll
    or pitch column (a receiver without an INS); ``gnss`` False: no gnss section (``start``: the drive's start:
    section); ``prior``: its prior: section."""
    import yaml

    columns = {"lat": "latitude_deg", "lon": "longitude_deg", "height": "height_m", "roll": "roll_deg",
               "pitch": "pitch_deg", "heading": "azimuth_deg", "std_east": "std_lon_m", "std_north": "std_lat_m",
               "std_up": "std_height_m", "std_heading": "std_azimuth_deg"}
    if not gnss_attitude:
        del columns["roll"], columns["pitch"]
    doc = {
        "name": name,
        "sensor": sensor,
        "scans": {"folder": "scans", "format": "pcd"},
        "scan_rate_hz": 10.0,
        "T_vehicle_lidar": [[float(v) for v in row] for row in T_vehicle_lidar],
        "gnss": {
            "file": "gnss_inspva.csv",
            "time": {"column": "gps_seconds", "week_column": "gps_week", "base": "gps"},
            "columns": columns,
            "angle_unit": "deg",
            "heading_convention": "azimuth_cw_from_north",
            "lever_arm_m": [0.0, 0.0, 0.0],
        },
        "odometry": {"file": "wheel_gyro.csv", "time_column": "gps_seconds", "week_column": "gps_week",
                     "speed": "wheel_speed_mps",
                     "yaw_rate": "yaw_rate_radps"},
        "scan_times": {"source": "pcd_field"},
    }
    if not gnss:
        del doc["gnss"]
        if start is not None:
            doc["start"] = start
    if prior is not None:
        doc["prior"] = prior
    if survey_crs:
        doc["survey"] = {"file": f"../{survey_dir}/survey.las", "crs": survey_crs}
    under = "under the lidar" if not np.any(np.asarray(T_vehicle_lidar, float)[:2, 3]) else \
        "at the vehicle's reference point\n# (the lidar at T_vehicle_lidar)"
    text = ("# Simulated drive (cornermap simulate). Vehicle frame: x forward, y left, z up, origin on the ground\n"
            f"# {under}. Scan stamps (scan start, GPS week + seconds of week) are in scans/stamps.csv.\n")
    path.write_text(text + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110))


def write_las(path: Path, xyz: np.ndarray, intensity: np.ndarray, epsg: int) -> None:
    """LAS 1.4, point format 6, CRS as WKT in the file; fixed creation date and identifiers."""
    import laspy
    from pyproj import CRS

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = np.floor(xyz.min(axis=0) / 1000.0) * 1000.0
    header.scales = np.array([0.001, 0.001, 0.001])
    header.add_crs(CRS.from_epsg(epsg))
    header.system_identifier = "cornermap simulate"
    header.generating_software = "cornermap simulate"
    header.creation_date = _dt.date(2016, 3, 15)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = intensity.astype(np.uint16)
    try:
        las.write(str(path))
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot write the survey LAS ({exc})") from exc


def write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), image):
        raise DatasetIOError(f"{path}: cv2.imwrite failed for a {image.shape} {image.dtype} raster")


def write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1, sort_keys=True) + "\n")
