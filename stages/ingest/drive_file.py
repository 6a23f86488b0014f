"""The drive file (``drive.yaml``): one recorded drive. Strictly validated; every problem listed at once.

Paths inside are relative to the drive file's folder and may not leave that folder's parent directory
(drives share e.g. ``../survey/``). The check is lexical (``..`` segments, absolute paths); symbolic links
placed inside the tree by the data owner are followed.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from pipeline.errors import ConfigError, DatasetIOError
from stages.ingest.scan_format_table import SCAN_FORMAT_NAMES

MAX_DRIVE_FILE_BYTES = 1 << 20  # a drive file is a few kB
TIME_UNIT_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}  # gnss.time.unit, odometry.time_unit


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScansSpec(_Strict):
    folder: str
    format: Literal[SCAN_FORMAT_NAMES]  # type: ignore[valid-type]  # the scan format table's names
    ring_from: Literal["auto", "file", "elevation_table", "point_order"] = "auto"


class GnssTime(_Strict):
    column: str
    week_column: str | None = None  # GPS week: stamp = week * 604800 s + seconds
    base: Literal["gps", "unix"] = "gps"
    unit: Literal["s", "ms", "us", "ns"] = "s"  # of the time column (ROS exports: ns)
    nanosec_column: str | None = None  # adds its nanoseconds (ROS header.stamp.secs + header.stamp.nsecs)


class GnssColumns(_Strict):
    lat: str
    lon: str
    height: str  # WGS84 ellipsoidal height, metres
    heading: str
    roll: str | None = None
    pitch: str | None = None
    std_east: str | None = None
    std_north: str | None = None
    std_up: str | None = None
    std_heading: str | None = None
    undulation: str | None = None  # geoid height above the ellipsoid (NovAtel INSPVAX): height + undulation


GNSS_FORMATS = ("csv", "kitti_oxts")


class GnssSpec(_Strict):
    file: str
    format: Literal["csv", "kitti_oxts"] = "csv"  # kitti_oxts: a folder with data/*.txt and timestamps.txt
    time: GnssTime
    columns: GnssColumns
    angle_unit: Literal["deg", "rad"] = "deg"  # roll, pitch, heading and std_heading
    latlon_unit: Literal["deg", "rad"] = "deg"
    heading_convention: Literal["azimuth_cw_from_north", "enu_yaw_ccw_from_east"]
    std_is_variance: bool = False  # the std columns hold variances (m^2; angle_unit^2): ROS position_covariance
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # GNSS/INS reference point in the vehicle frame


class OdometrySpec(_Strict):
    file: str
    format: Literal["csv", "kitti_oxts"] = "csv"
    time_column: str
    time_unit: Literal["s", "ms", "us", "ns"] = "s"
    nanosec_column: str | None = None
    week_column: str | None = None
    speed: str  # m/s
    yaw_rate: str  # rad/s


class SurveySpec(_Strict):
    file: str
    crs: str  # e.g. "EPSG:32652" (UTM 52N), "EPSG:28992" (RD New)


class ScanTimesSpec(_Strict):
    # pcd_field / stamps_csv: scan stamps from a CSV (scan_id, gps_seconds[, gps_week]); per-point times
    # from the PCD time field. rate: scan i at t0 + i / scan_rate_hz (t0_s, else the first GNSS fix, else 0).
    # filename_us: stamp in microseconds at the end of the file name (nuScenes ``...__1532402927647951``).
    # stamps_lines: one stamp per line, line k = scan k (KITTI ``timestamps.txt``; numbers or date-times).
    source: Literal["pcd_field", "stamps_csv", "rate", "filename_us", "stamps_lines"] = "rate"
    file: str | None = None  # default <scans folder>/stamps.csv (stamps_lines: required)
    t0_s: float | None = None


class GeodeticPoint(_Strict):
    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    h_m: float = Field(ge=-1000, le=10000)  # WGS84 ellipsoidal


class PriorSpec(_Strict):
    """A trajectory the drive comes with (SLAM poses of a keyframe dataset, a post-processed INS): ingest decodes it
    into ``poses_prior``."""

    file: str
    format: Literal["tum", "kitti"]  # tum: t x y z qx qy qz qw; kitti: 12 numbers (3x4 row-major) per line
    frame: Literal["enu", "local"]  # enu: ENU about ``origin``; local: z up, origin and heading unknown
    origin: GeodeticPoint | None = None  # the ENU origin of an ``enu`` file
    time: Literal["stamps", "scan_order"] = "stamps"  # stamps: tum t in the drive's time base; scan_order: row k
    body: Literal["vehicle", "lidar"] = "vehicle"  # whose poses the file holds
    std_m: tuple[float, float, float] = (0.1, 0.1, 0.1)  # per axis of the file's frame (x y z)
    std_deg: tuple[float, float, float] = (0.1, 0.1, 0.5)  # roll, pitch, yaw

    @field_validator("std_m", "std_deg")
    @classmethod
    def _positive(cls, v):
        if any(not np.isfinite(x) or x <= 0 for x in v):
            raise ValueError("every std must be a positive number")
        return v


class StartSpec(_Strict):
    """Where and how the drive starts, for a drive with no GNSS: its first scan's vehicle pose is at ``position``
    (default: the map's origin, ``cornermap build --origin``) with this heading."""

    heading_deg: float = Field(ge=-360, le=360)
    heading_convention: Literal["azimuth_cw_from_north", "enu_yaw_ccw_from_east"]
    std_heading_deg: float = Field(1.0, gt=0)
    position: GeodeticPoint | None = None  # None: the map's origin
    std_m: float = Field(0.5, gt=0)  # of ``position`` (horizontal); the map's origin is exact


class DriveSpec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    sensor: str  # a model of stages/ingest/sensors.py SENSORS
    elevations_deg: tuple[float, ...] | None = None  # overrides the sensor's table (ascending)
    calibration_file: str | None = None  # the sensor's own table (Ouster metadata JSON, Velodyne db.xml, Hesai CSV)
    scans: ScansSpec
    scan_rate_hz: float = Field(gt=0, le=100)
    T_vehicle_lidar: tuple[tuple[float, float, float, float], ...]
    gnss: GnssSpec | None = None
    odometry: OdometrySpec | None = None
    survey: SurveySpec | None = None
    scan_times: ScanTimesSpec = ScanTimesSpec()
    prior: PriorSpec | None = None
    start: StartSpec | None = None
    drive_dir: Path = Field(default=Path("."), exclude=True)  # set by load_drive_file

    @field_validator("T_vehicle_lidar")
    @classmethod
    def _rigid(cls, rows):
        T = np.asarray(rows, float)
        if T.shape != (4, 4):
            raise ValueError(f"expected a 4x4 matrix, got {T.shape[0]} rows")
        R = T[:3, :3]
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) \
                or np.linalg.det(R) < 0:
            raise ValueError("not a rigid transform (last row 0 0 0 1, orthonormal rotation with det +1)")
        return rows

    @field_validator("sensor")
    @classmethod
    def _known_sensor(cls, v):
        from pipeline.names import suggest
        from stages.ingest.sensors import SENSORS

        if v not in SENSORS:
            raise ValueError(f"unknown sensor {v!r}; expected one of {', '.join(SENSORS)}{suggest(v, SENSORS)}")
        return v

    @field_validator("elevations_deg")
    @classmethod
    def _ascending(cls, v):
        if v is not None and (len(v) < 1 or np.any(np.diff(v) <= 0)):
            raise ValueError("elevations_deg must be a non-empty ascending list (ring 0 = lowest beam)")
        return v

    def path(self, relative: str) -> Path:
        return Path(os.path.normpath(self.drive_dir / relative))

    @property
    def T_vehicle_lidar_matrix(self) -> np.ndarray:
        return np.asarray(self.T_vehicle_lidar, float)

    @property
    def stamps_file(self) -> Path:
        return self.path(self.scan_times.file or f"{self.scans.folder}/stamps.csv")


def _format_pydantic(err: ValidationError) -> list[str]:
    out = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = "unknown key (not allowed)" if e["type"] == "extra_forbidden" else e["msg"]
        got = "" if e["type"] in ("missing", "extra_forbidden") else f" (got {e.get('input')!r})"
        out.append(f"{loc}: {msg}{got}")
    return out


def _path_problems(spec: DriveSpec) -> list[str]:
    fence = os.path.normpath(spec.drive_dir.parent)
    wanted: list[tuple[str, str, str]] = [("scans.folder", spec.scans.folder, "dir")]
    if spec.gnss:
        wanted.append(("gnss.file", spec.gnss.file, "dir" if spec.gnss.format == "kitti_oxts" else "file"))
    if spec.odometry:
        wanted.append(("odometry.file", spec.odometry.file, "dir" if spec.odometry.format == "kitti_oxts" else "file"))
    if spec.survey:
        wanted.append(("survey.file", spec.survey.file, "file"))
    if spec.calibration_file:
        wanted.append(("calibration_file", spec.calibration_file, "file"))
    if spec.prior:
        wanted.append(("prior.file", spec.prior.file, "file"))
    if spec.scan_times.source == "stamps_lines" and spec.scan_times.file:
        wanted.append(("scan_times.file", spec.scan_times.file, "file"))
    if spec.scan_times.source in ("pcd_field", "stamps_csv"):
        wanted.append(("scan_times.file", str(spec.stamps_file.relative_to(spec.drive_dir)
                                              if spec.stamps_file.is_relative_to(spec.drive_dir)
                                              else spec.stamps_file), "file"))
    problems = []
    for key, rel, kind in wanted:
        full = spec.path(rel)
        if os.path.commonpath([fence, str(full)]) != fence:
            problems.append(f"{key}: {rel!r} resolves to {full}, outside the drive's parent folder {fence}; "
                            f"refused (keep drive data under {fence})")
        elif kind == "dir" and not full.is_dir():
            problems.append(f"{key}: folder {full} does not exist" + (" (it is a file)" if full.is_file() else ""))
        elif kind == "file" and not full.is_file():
            problems.append(f"{key}: file {full} does not exist")
    return problems


def _semantic_problems(spec: DriveSpec) -> list[str]:
    problems = []
    if spec.scans.ring_from == "file" and spec.scans.format == "kitti_bin":
        problems.append("scans.ring_from: 'file' but kitti_bin files carry no ring; use point_order")
    if spec.scans.ring_from == "elevation_table" and spec.sensor == "generic" and not spec.elevations_deg \
            and not spec.calibration_file:
        problems.append("scans.ring_from: elevation_table needs elevations_deg or calibration_file for the generic "
                        "sensor")
    if spec.scan_times.source == "stamps_lines" and not spec.scan_times.file:
        problems.append("scan_times.file: source stamps_lines needs the file of one stamp per line (e.g. "
                        "velodyne_points/timestamps.txt)")
    if spec.prior:
        p = spec.prior
        if p.format == "kitti" and p.time != "scan_order":
            problems.append("prior.time: a kitti poses file has no times; use time: scan_order (line k = scan k)")
        if p.frame == "enu" and p.origin is None:
            problems.append("prior.origin: frame enu needs the file's ENU origin {lat_deg, lon_deg, h_m}")
        if p.frame == "local" and p.origin is not None:
            problems.append("prior.origin: a local frame has no geodetic origin; use frame: enu for ENU about it")
    if spec.survey:
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            CRS.from_user_input(spec.survey.crs)
        except CRSError:
            problems.append(f"survey.crs: {spec.survey.crs!r} is not a CRS pyproj knows (e.g. 'EPSG:28992')")
    return problems


def parse_drive_file(raw: object, drive_dir: Path, where: str) -> DriveSpec:
    """Validate an already-loaded mapping; raise one ConfigError listing every problem."""
    if not isinstance(raw, dict):
        raise ConfigError(where, [f"expected a mapping at the top level, got {type(raw).__name__}"])
    try:
        spec = DriveSpec.model_validate({**raw, "drive_dir": Path(os.path.abspath(drive_dir))})
    except ValidationError as exc:
        raise ConfigError(where, _format_pydantic(exc)) from None
    problems = _path_problems(spec) + _semantic_problems(spec)
    if problems:
        raise ConfigError(where, problems)
    return spec


def load_drive_file(path: str | Path) -> DriveSpec:
    """Read and validate a drive file. Parsed with bounded work (size cap, no aliases, duplicate keys refused:
    ``pipeline.safe_yaml``), so an untrusted drive folder cannot exhaust memory or hide a key."""
    from pipeline.safe_yaml import load_yaml

    path = Path(path)
    try:
        raw_bytes = path.read_bytes() if path.stat().st_size <= MAX_DRIVE_FILE_BYTES else None
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read drive file: {exc.strerror or exc}. Hint: check the "
                             f"workflow's drive path") from exc
    if raw_bytes is None:
        raise ConfigError(str(path), [f"{path.stat().st_size} bytes, more than the {MAX_DRIVE_FILE_BYTES}-byte "
                                      f"limit of a drive file"])
    return parse_drive_file(load_yaml(raw_bytes, str(path), max_bytes=MAX_DRIVE_FILE_BYTES), path.parent,
                            str(path))
