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

MAX_DRIVE_FILE_BYTES = 1 << 20  # a drive file is a few kB


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScansSpec(_Strict):
    folder: str
    format: Literal["pcd", "kitti_bin", "nuscenes_bin", "las"]
    ring_from: Literal["auto", "file", "elevation_table", "point_order"] = "auto"


class GnssTime(_Strict):
    column: str
    week_column: str | None = None  # GPS week: stamp = week * 604800 s + seconds
    base: Literal["gps", "unix"] = "gps"


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


class GnssSpec(_Strict):
    file: str
    time: GnssTime
    columns: GnssColumns
    angle_unit: Literal["deg", "rad"] = "deg"  # roll, pitch, heading and std_heading
    latlon_unit: Literal["deg", "rad"] = "deg"
    heading_convention: Literal["azimuth_cw_from_north", "enu_yaw_ccw_from_east"]
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # GNSS/INS reference point in the vehicle frame


class OdometrySpec(_Strict):
    file: str
    time_column: str
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
    source: Literal["pcd_field", "stamps_csv", "rate", "filename_us"] = "rate"
    file: str | None = None  # default <scans folder>/stamps.csv
    t0_s: float | None = None


class DriveSpec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
    sensor: Literal["hdl32e", "hdl64e", "vlp16", "generic"]
    elevations_deg: tuple[float, ...] | None = None  # overrides the sensor's table (ascending)
    scans: ScansSpec
    scan_rate_hz: float = Field(gt=0, le=100)
    T_vehicle_lidar: tuple[tuple[float, float, float, float], ...]
    gnss: GnssSpec | None = None
    odometry: OdometrySpec | None = None
    survey: SurveySpec | None = None
    scan_times: ScanTimesSpec = ScanTimesSpec()
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
        wanted.append(("gnss.file", spec.gnss.file, "file"))
    if spec.odometry:
        wanted.append(("odometry.file", spec.odometry.file, "file"))
    if spec.survey:
        wanted.append(("survey.file", spec.survey.file, "file"))
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
            problems.append(f"{key}: folder {full} does not exist")
        elif kind == "file" and not full.is_file():
            problems.append(f"{key}: file {full} does not exist")
    return problems


def _semantic_problems(spec: DriveSpec) -> list[str]:
    problems = []
    if spec.scans.ring_from == "file" and spec.scans.format == "kitti_bin":
        problems.append("scans.ring_from: 'file' but kitti_bin files carry no ring; use point_order")
    if spec.scans.ring_from == "elevation_table" and spec.sensor == "generic" and not spec.elevations_deg:
        problems.append("scans.ring_from: elevation_table needs elevations_deg for the generic sensor")
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
