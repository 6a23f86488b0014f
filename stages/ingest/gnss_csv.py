"""GNSS/INS and odometry CSV files -> float64 arrays, with time stamps as int64 ns in the drive's time base.

``record`` numbers in problems and reports are 0-based data rows (file line = record + 2 with one header line).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import FormatError
from stages.ingest.csv_columns import TimestampIssue, read_csv_columns, read_header
from stages.ingest.drive_file import TIME_UNIT_S, GnssSpec, OdometrySpec

NS_PER_WEEK = 604_800 * 1_000_000_000


@dataclass(frozen=True)
class GnssFixes:
    """GNSS/INS solutions at the antenna / INS reference point (lever arm not yet applied)."""

    stamp_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h_m: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_enu_rad: np.ndarray  # counter-clockwise from east
    std_enu_m: np.ndarray  # (N, 3): the file's, or the documented default where it has none (never NaN)
    std_yaw_rad: np.ndarray
    records: np.ndarray  # 0-based data row of each kept fix
    roll_pitch_known: bool = True  # false: the file has no roll/pitch (stored as 0, never used as a prior)
    defaults_used: tuple[str, ...] = ()  # names of the std columns that came from defaults


@dataclass(frozen=True)
class GnssLimits:
    """Sanity limits and defaults for GNSS/INS rows (from the ingest params)."""

    default_std_enu_m: tuple[float, float, float] = (1.0, 1.0, 2.0)
    default_std_heading_rad: float = 0.0175
    height_range_m: tuple[float, float] = (-1000.0, 10000.0)
    max_speed_mps: float = 100.0


def stamps_ns(seconds: np.ndarray, week: np.ndarray | None = None) -> np.ndarray:
    """Seconds (float64) [+ GPS week] -> int64 ns: week * 604800 s + seconds, rounded to the nanosecond."""
    seconds = np.asarray(seconds, np.float64)
    ns = np.round(seconds * 1e9).astype(np.int64)
    if week is not None:
        ns = ns + np.round(np.asarray(week, np.float64)).astype(np.int64) * NS_PER_WEEK
    return ns


def monotonic_mask(stamp_ns: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, list[TimestampIssue]]:
    """Keep rows whose stamp is strictly after every earlier kept stamp; report the others by record."""
    valid = np.ones(len(stamp_ns), bool) if valid is None else valid
    issues = [TimestampIssue(int(i), "missing or non-finite time") for i in np.flatnonzero(~valid)]
    masked = np.where(valid, stamp_ns, np.iinfo(np.int64).min)
    prev_max = np.maximum.accumulate(np.concatenate([[np.iinfo(np.int64).min], masked[:-1]]))
    dup = valid & (stamp_ns == prev_max)
    back = valid & (stamp_ns < prev_max)
    issues += [TimestampIssue(int(i), "duplicate timestamp") for i in np.flatnonzero(dup)]
    issues += [TimestampIssue(int(i), f"timestamp goes back {(prev_max[i] - stamp_ns[i]) / 1e9:.6f} s")
               for i in np.flatnonzero(back)]
    return valid & ~dup & ~back, sorted(issues, key=lambda t: t.record)


def find_gaps(stamp_ns: np.ndarray, max_gap_s: float) -> list[tuple[int, float]]:
    """(index of the fix before the gap, gap length s) for every gap longer than ``max_gap_s``."""
    dt_s = np.diff(stamp_ns) / 1e9
    return [(int(i), float(dt_s[i])) for i in np.flatnonzero(dt_s > max_gap_s)]


def _time_columns(spec_time_column: str, week_column: str | None, nanosec_column: str | None = None) -> list[str]:
    return [spec_time_column] + ([week_column] if week_column else []) + ([nanosec_column] if nanosec_column else [])


def read_gnss(path: Path, spec: GnssSpec, limits: GnssLimits = GnssLimits()
              ) -> tuple[GnssFixes, list[TimestampIssue]]:
    """GNSS/INS rows -> fixes. Rows are rejected one by one with a reason (non-numeric cell, missing or
    non-monotonic time, latitude/longitude/height out of range after unit conversion, a jump faster than
    ``limits.max_speed_mps`` from the previous kept fix); the drive fails only if the file cannot be read."""
    c = spec.columns
    optional = {k: getattr(c, k) for k in ("roll", "pitch", "std_east", "std_north", "std_up", "std_heading",
                                            "undulation")}
    names = _time_columns(spec.time.column, spec.time.week_column, spec.time.nanosec_column) + \
        [c.lat, c.lon, c.height, c.heading] + \
        [v for v in optional.values() if v]
    bad_cells: list[TimestampIssue] = []
    cols = read_csv_columns(path, names, bad_cells=bad_cells)
    n = len(cols[c.lat])
    week = cols[spec.time.week_column] if spec.time.week_column else None
    seconds = cols[spec.time.column] * TIME_UNIT_S[spec.time.unit] + \
        (cols[spec.time.nanosec_column] * 1e-9 if spec.time.nanosec_column else 0.0)
    finite = np.isfinite(seconds) & (np.isfinite(week) if week is not None else True)
    stamp = stamps_ns(np.where(finite, seconds, 0.0), None if week is None else np.where(finite, week, 0.0))
    keep, issues = monotonic_mask(stamp, finite)
    bad_rows = {i.record for i in bad_cells}  # reported once, with the cell that was not a number
    issues = [i for i in issues if i.record not in bad_rows] + bad_cells
    keep[sorted(bad_rows)] = False
    values_ok = np.isfinite(cols[c.lat]) & np.isfinite(cols[c.lon]) & np.isfinite(cols[c.height]) & \
        np.isfinite(cols[c.heading])
    issues += [TimestampIssue(int(i), "non-finite lat/lon/height/heading") for i in np.flatnonzero(keep & ~values_ok)]
    keep &= values_ok
    angle = np.pi / 180.0 if spec.angle_unit == "deg" else 1.0
    latlon = 1.0 if spec.latlon_unit == "deg" else 180.0 / np.pi
    lat, lon, h = cols[c.lat] * latlon, cols[c.lon] * latlon, cols[c.height] + (cols[c.undulation] if c.undulation
                                                                                else 0.0)
    unit = f"latlon_unit {spec.latlon_unit}"
    checks = ((np.abs(lat) > 90.0, f"latitude outside -90..90 deg ({unit})"),
              (np.abs(lon) > 180.0, f"longitude outside -180..180 deg ({unit})"),
              ((h < limits.height_range_m[0]) | (h > limits.height_range_m[1]),
               f"height outside {limits.height_range_m[0]:g}..{limits.height_range_m[1]:g} m"))
    for out_of_range, why in checks:  # one reason per row: the first check it fails
        bad = keep & out_of_range
        issues += [TimestampIssue(int(i), f"{why}: {lat[i]:.6g}, {lon[i]:.6g}, {h[i]:.6g}")
                   for i in np.flatnonzero(bad)]
        keep &= ~bad
    jumps = _speed_outliers(stamp, lat, lon, keep, limits.max_speed_mps)
    issues += [TimestampIssue(int(i), f"position jumps {v:.0f} m/s from the previous fix (limit "
                                      f"{limits.max_speed_mps:g} m/s)") for i, v in jumps]
    keep[[i for i, _ in jumps]] = False
    if spec.latlon_unit == "deg":
        _refuse_radians_as_degrees(path, stamp[keep], lat[keep], lon[keep], limits.max_speed_mps)

    def opt(key: str, scale: float = 1.0) -> np.ndarray:
        return cols[optional[key]] * scale if optional[key] else np.full(n, np.nan)

    heading = cols[c.heading] * angle
    yaw = heading if spec.heading_convention == "enu_yaw_ccw_from_east" else np.pi / 2 - heading
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    defaults = []
    std = np.column_stack([opt("std_east"), opt("std_north"), opt("std_up")])
    if spec.std_is_variance:  # ROS covariances (m^2): the std is the square root
        std = np.sqrt(np.where(std > 0, std, np.nan))
    for axis, key in enumerate(("std_east", "std_north", "std_up")):
        missing = ~np.isfinite(std[:, axis]) | (std[:, axis] <= 0)
        if np.any(missing & keep):
            defaults.append(key)
            std[missing, axis] = limits.default_std_enu_m[axis]
    std_yaw = np.sqrt(np.where(opt("std_heading") > 0, opt("std_heading"), np.nan)) * angle \
        if spec.std_is_variance else opt("std_heading", angle)
    missing = ~np.isfinite(std_yaw) | (std_yaw <= 0)
    if np.any(missing & keep):
        defaults.append("std_heading")
        std_yaw[missing] = limits.default_std_heading_rad
    roll_pitch_known = bool(optional["roll"] and optional["pitch"])
    fixes = GnssFixes(
        stamp[keep], lat[keep], lon[keep], h[keep],
        np.nan_to_num(opt("roll", angle))[keep], np.nan_to_num(opt("pitch", angle))[keep], yaw[keep],
        std[keep], std_yaw[keep], np.flatnonzero(keep), roll_pitch_known, tuple(defaults))
    return fixes, sorted(issues, key=lambda t: t.record)


EARTH_RADIUS_M = 6_371_000.0
SLOW_AS_DEGREES_MPS = 0.5  # a survey track this slow on average, that is a plausible drive as radians: radians


def _track_speed_mps(stamp_ns: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray) -> float:
    """Mean speed along a track (path length over duration), local equirectangular distances."""
    east = lon_rad * EARTH_RADIUS_M * np.cos(np.median(lat_rad))
    north = lat_rad * EARTH_RADIUS_M
    duration_s = (stamp_ns[-1] - stamp_ns[0]) / 1e9
    return float(np.hypot(np.diff(east), np.diff(north)).sum() / duration_s) if duration_s > 0 else 0.0


def _refuse_radians_as_degrees(path: Path, stamp_ns: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray,
                               max_speed_mps: float) -> None:
    """FormatError when fixes declared in degrees are radians: every latitude within +-pi/2 and longitude within +-pi
    (as degrees: a few hundred km around 0 N 0 E, open sea but for a strip of coast) and the track, slower than
    ``SLOW_AS_DEGREES_MPS`` as degrees, is a plausible drive as radians (1 m/s up to the speed limit). A drive parked
    all along passes here; its distance from the map's origin (``check_within_area``) stops it then."""
    if len(lat_deg) < 2 or np.abs(lat_deg).max() > np.pi / 2 or np.abs(lon_deg).max() > np.pi:
        return
    as_degrees = _track_speed_mps(stamp_ns, np.radians(lat_deg), np.radians(lon_deg))
    as_radians = _track_speed_mps(stamp_ns, lat_deg, lon_deg)
    if as_degrees < SLOW_AS_DEGREES_MPS and 1.0 <= as_radians <= max_speed_mps:
        raise FormatError(
            f"{path}: every latitude/longitude lies within +-pi/2 / +-pi (latitude {lat_deg.min():.6g}.."
            f"{lat_deg.max():.6g}, longitude {lon_deg.min():.6g}..{lon_deg.max():.6g}); read as degrees the track "
            f"moves at {as_degrees:.3f} m/s, read as radians at {as_radians:.1f} m/s: these are radians, but the "
            "drive file says degrees "
            "(gnss.latlon_unit: deg, the default); expected degrees. hint: set gnss.latlon_unit: rad")


def check_within_area(fixes: GnssFixes, origin, max_radius_m: float | None, drive: str, file: str) -> None:
    """DataQualityError (exit 3) when a fix lies farther than ``max_radius_m`` (horizontal) from the map's ENU origin
    ``origin``: a local ENU frame is a tangent plane, and the map's area is bounded (docs/maintenance.md)."""
    from pipeline.errors import DataQualityError
    from stages.common.geodesy import geodetic_to_enu

    if max_radius_m is None or origin is None or not len(fixes.stamp_ns):
        return
    enu = geodetic_to_enu(fixes.lat_deg, fixes.lon_deg, fixes.h_m, origin)
    dist = np.hypot(enu[:, 0], enu[:, 1])
    worst = int(np.argmax(dist))
    if dist[worst] > max_radius_m:
        raise DataQualityError(
            f"drive {drive}: {file} record {int(fixes.records[worst])} lies {dist[worst] / 1000:.1f} km from the map's "
            f"origin ({origin.lat_deg:.6f}, {origin.lon_deg:.6f}), {int((dist > max_radius_m).sum())} of "
            f"{len(dist)} fixes beyond the map's area of {max_radius_m / 1000:g} km; refused (a local ENU frame "
            "does not reach that far). hint: build it into a map of its own, or check the GNSS file")


def _speed_outliers(stamp_ns: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray, keep: np.ndarray,
                    max_speed_mps: float) -> list[tuple[int, float]]:
    """Rows further from the previous accepted row than ``max_speed_mps`` allows. The walk starts at the row
    nearest the median position (so a bad first row cannot reject the rest) and goes forward and backward; a
    rejected row is never the reference for the next one. Local equirectangular distances: exact enough to
    find jumps of kilometres."""
    idx = np.flatnonzero(keep)
    if len(idx) < 2:
        return []
    east = np.radians(lon_deg[idx]) * 6_371_000.0 * np.cos(np.radians(np.median(lat_deg[idx])))
    north = np.radians(lat_deg[idx]) * 6_371_000.0
    start = int(np.argmin(np.hypot(east - np.median(east), north - np.median(north))))
    out: list[tuple[int, float]] = []
    for order in (range(start + 1, len(idx)), range(start - 1, -1, -1)):
        last = start
        for k in order:  # per fix, sequential by construction
            dt_s = max(abs(stamp_ns[idx[k]] - stamp_ns[idx[last]]) / 1e9, 1e-3)
            speed = float(np.hypot(east[k] - east[last], north[k] - north[last]) / dt_s)
            if speed > max_speed_mps:
                out.append((int(idx[k]), speed))
            else:
                last = k
    return sorted(out)


def read_first_fix(path: Path, spec: GnssSpec) -> tuple[float, float, float] | None:
    """(lat_deg, lon_deg, h_m) of the first data row with finite values, reading only the file's head."""
    header = read_header(path)
    c = spec.columns
    if Path(path).is_dir() or c.undulation:  # a KITTI OXTS folder, or height + undulation: read as columns
        return _first_fix_from_columns(path, spec)
    try:
        idx = [header.index(k) for k in (c.lat, c.lon, c.height)]
    except ValueError:
        raise FormatError(f"{path}: CSV lacks one of {c.lat}, {c.lon}, {c.height}; header has "
                          f"{', '.join(header)}") from None
    scale = 1.0 if spec.latlon_unit == "deg" else 180.0 / np.pi
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        rows = csv.reader(fh)
        next(rows, None)
        for row in rows:
            try:
                lat, lon, h = (float(row[i]) for i in idx)
            except (ValueError, IndexError):
                continue
            if np.isfinite([lat, lon, h]).all():
                return lat * scale, lon * scale, h
    return None


def _first_fix_from_columns(path: Path, spec: GnssSpec) -> tuple[float, float, float] | None:
    c = spec.columns
    cols = read_csv_columns(path, [c.lat, c.lon, c.height] + ([c.undulation] if c.undulation else []),
                            bad_cells=[])
    scale = 1.0 if spec.latlon_unit == "deg" else 180.0 / np.pi
    h = cols[c.height] + (cols[c.undulation] if c.undulation else 0.0)
    ok = np.flatnonzero(np.isfinite(cols[c.lat]) & np.isfinite(cols[c.lon]) & np.isfinite(h))
    return None if not len(ok) else (float(cols[c.lat][ok[0]]) * scale, float(cols[c.lon][ok[0]]) * scale,
                                     float(h[ok[0]]))


def read_odometry(path: Path, spec: OdometrySpec) -> tuple[dict[str, np.ndarray], list[TimestampIssue]]:
    cols = read_csv_columns(path, _time_columns(spec.time_column, spec.week_column, spec.nanosec_column)
                            + [spec.speed, spec.yaw_rate])
    seconds = cols[spec.time_column] * TIME_UNIT_S[spec.time_unit] + \
        (cols[spec.nanosec_column] * 1e-9 if spec.nanosec_column else 0.0)
    week = cols[spec.week_column] if spec.week_column else None
    finite = np.isfinite(seconds) & (np.isfinite(week) if week is not None else True)
    stamp = stamps_ns(np.where(finite, seconds, 0.0), None if week is None else np.where(finite, week, 0.0))
    keep, issues = monotonic_mask(stamp, finite)
    return {"stamp_ns": stamp[keep], "speed_mps": cols[spec.speed][keep],
            "yaw_rate_radps": cols[spec.yaw_rate][keep]}, issues


def read_scan_stamps(path: Path, default_week: int | None, max_scan_id: int = 100_000_000
                     ) -> tuple[dict[int, int], list[TimestampIssue]]:
    """``scan_id, gps_seconds[, gps_week]`` (or ``scan_id, stamp_ns``) -> ({scan_id: stamp_ns}, rejected rows).
    A row with a non-integer, negative or too large scan id (>= ``max_scan_id``), a repeated id or a
    non-finite time is rejected with its reason; the others are kept."""
    header = read_header(path)
    if "scan_id" not in header or not ({"gps_seconds", "stamp_ns"} & set(header)):
        raise FormatError(f"{path}: scan stamps need columns scan_id and gps_seconds (or stamp_ns); header has "
                          f"{', '.join(header)}")
    issues: list[TimestampIssue] = []
    if "stamp_ns" in header:
        cols = read_csv_columns(path, ["scan_id", "stamp_ns"], bad_cells=issues)
        ns = np.where(np.isfinite(cols["stamp_ns"]), cols["stamp_ns"], 0).astype(np.int64)
        ok_time = np.isfinite(cols["stamp_ns"])
    else:
        names = ["scan_id", "gps_seconds"] + (["gps_week"] if "gps_week" in header else [])
        cols = read_csv_columns(path, names, bad_cells=issues)
        week = cols.get("gps_week")
        if week is None and default_week is not None:
            week = np.full(len(cols["scan_id"]), float(default_week))
        ok_time = np.isfinite(cols["gps_seconds"]) & (np.isfinite(week) if week is not None else True)
        ns = stamps_ns(np.where(ok_time, cols["gps_seconds"], 0.0),
                       None if week is None else np.where(np.isfinite(week), week, 0.0))
    out: dict[int, int] = {}
    for record, (sid, t, ok) in enumerate(zip(cols["scan_id"], ns, ok_time)):
        if not np.isfinite(sid) or sid != np.floor(sid) or not 0 <= sid < max_scan_id:
            issues.append(TimestampIssue(record, f"scan_id {sid!r} is not an integer in 0..{max_scan_id - 1}"))
        elif not ok:
            issues.append(TimestampIssue(record, f"scan {int(sid)}: missing or non-finite time"))
        elif int(sid) in out:
            issues.append(TimestampIssue(record, f"scan {int(sid)} is listed twice (first row kept)"))
        else:
            out[int(sid)] = int(t)
    return out, sorted(issues, key=lambda t: t.record)
