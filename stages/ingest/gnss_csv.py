"""GNSS/INS and odometry CSV files -> float64 arrays, with time stamps as int64 ns in the drive's time base.

``record`` numbers in problems and reports are 0-based data rows (file line = record + 2 with one header line).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError
from stages.ingest.drive_file import GnssSpec, OdometrySpec

NS_PER_WEEK = 604_800 * 1_000_000_000


@dataclass(frozen=True)
class TimestampIssue:
    record: int
    reason: str


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
    std_enu_m: np.ndarray  # (N, 3), NaN where the file has none
    std_yaw_rad: np.ndarray
    records: np.ndarray  # 0-based data row of each kept fix


def read_header(path: Path, delimiter: str = ",") -> list[str]:
    try:
        with open(path, newline="") as fh:
            return [c.strip() for c in next(csv.reader(fh, delimiter=delimiter), [])]
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read CSV: {exc.strerror or exc}") from exc


def read_csv_columns(path: Path, names: list[str], delimiter: str = ",") -> dict[str, np.ndarray]:
    """Named columns as float64. Rows with the wrong number of values or non-numeric cells raise FormatError
    listing them (up to 10) with their record numbers."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    header = read_header(path, delimiter)
    missing = [n for n in dict.fromkeys(names) if n not in header]
    if missing:
        raise FormatError(f"{path}: CSV lacks column(s) {', '.join(missing)}; header has {', '.join(header)}. "
                          f"Hint: fix the column mapping in drive.yaml")
    bad: list[str] = []

    def on_invalid(row) -> str:
        line = f"line {row.number}" if row.number is not None else "a row"
        bad.append(f"{line}: {row.actual_columns} values, expected {row.expected_columns}")
        return "skip"

    try:
        table = pacsv.read_csv(
            path, read_options=pacsv.ReadOptions(use_threads=False),
            parse_options=pacsv.ParseOptions(delimiter=delimiter, invalid_row_handler=on_invalid),
            convert_options=pacsv.ConvertOptions(include_columns=list(dict.fromkeys(names)),
                                                 column_types={n: pa.float64() for n in names}))
    except pa.ArrowInvalid as exc:
        raise FormatError(f"{path}: unreadable CSV: {exc}. Hint: a cell is not a number") from exc
    if bad:
        raise FormatError(f"{path}: {len(bad)} row(s) with the wrong number of columns: " + "; ".join(bad[:10]))
    return {n: table[n].to_numpy(zero_copy_only=False).astype(np.float64) for n in names}


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


def _time_columns(spec_time_column: str, week_column: str | None) -> list[str]:
    return [spec_time_column] + ([week_column] if week_column else [])


def read_gnss(path: Path, spec: GnssSpec) -> tuple[GnssFixes, list[TimestampIssue]]:
    c = spec.columns
    optional = {k: getattr(c, k) for k in ("roll", "pitch", "std_east", "std_north", "std_up", "std_heading")}
    names = _time_columns(spec.time.column, spec.time.week_column) + [c.lat, c.lon, c.height, c.heading] + \
        [v for v in optional.values() if v]
    cols = read_csv_columns(path, names)
    n = len(cols[c.lat])
    week = cols[spec.time.week_column] if spec.time.week_column else None
    seconds = cols[spec.time.column]
    finite = np.isfinite(seconds) & (np.isfinite(week) if week is not None else True)
    stamp = stamps_ns(np.where(finite, seconds, 0.0), None if week is None else np.where(finite, week, 0.0))
    keep, issues = monotonic_mask(stamp, finite)
    values_ok = np.isfinite(cols[c.lat]) & np.isfinite(cols[c.lon]) & np.isfinite(cols[c.height]) & \
        np.isfinite(cols[c.heading])
    issues = sorted(issues + [TimestampIssue(int(i), "non-finite lat/lon/height/heading")
                              for i in np.flatnonzero(keep & ~values_ok)], key=lambda t: t.record)
    keep &= values_ok
    angle = np.pi / 180.0 if spec.angle_unit == "deg" else 1.0
    latlon = 1.0 if spec.latlon_unit == "deg" else 180.0 / np.pi

    def opt(key: str, scale: float = 1.0) -> np.ndarray:
        return cols[optional[key]] * scale if optional[key] else np.full(n, np.nan)

    heading = cols[c.heading] * angle
    yaw = heading if spec.heading_convention == "enu_yaw_ccw_from_east" else np.pi / 2 - heading
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    fixes = GnssFixes(
        stamp[keep], cols[c.lat][keep] * latlon, cols[c.lon][keep] * latlon, cols[c.height][keep],
        np.nan_to_num(opt("roll", angle))[keep], np.nan_to_num(opt("pitch", angle))[keep], yaw[keep],
        np.column_stack([opt("std_east"), opt("std_north"), opt("std_up")])[keep], opt("std_heading", angle)[keep],
        np.flatnonzero(keep))
    return fixes, issues


def read_first_fix(path: Path, spec: GnssSpec) -> tuple[float, float, float] | None:
    """(lat_deg, lon_deg, h_m) of the first data row with finite values, reading only the file's head."""
    header = read_header(path)
    c = spec.columns
    try:
        idx = [header.index(k) for k in (c.lat, c.lon, c.height)]
    except ValueError:
        raise FormatError(f"{path}: CSV lacks one of {c.lat}, {c.lon}, {c.height}; header has "
                          f"{', '.join(header)}") from None
    scale = 1.0 if spec.latlon_unit == "deg" else 180.0 / np.pi
    with open(path, newline="") as fh:
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


def read_odometry(path: Path, spec: OdometrySpec) -> tuple[dict[str, np.ndarray], list[TimestampIssue]]:
    cols = read_csv_columns(path, _time_columns(spec.time_column, spec.week_column) + [spec.speed, spec.yaw_rate])
    seconds = cols[spec.time_column]
    week = cols[spec.week_column] if spec.week_column else None
    finite = np.isfinite(seconds) & (np.isfinite(week) if week is not None else True)
    stamp = stamps_ns(np.where(finite, seconds, 0.0), None if week is None else np.where(finite, week, 0.0))
    keep, issues = monotonic_mask(stamp, finite)
    return {"stamp_ns": stamp[keep], "speed_mps": cols[spec.speed][keep],
            "yaw_rate_radps": cols[spec.yaw_rate][keep]}, issues


def read_scan_stamps(path: Path, default_week: int | None) -> dict[int, int]:
    """``scan_id, gps_seconds[, gps_week]`` (or ``scan_id, stamp_ns``) -> {scan_id: stamp_ns}."""
    header = read_header(path)
    if "scan_id" not in header or not ({"gps_seconds", "stamp_ns"} & set(header)):
        raise FormatError(f"{path}: scan stamps need columns scan_id and gps_seconds (or stamp_ns); header has "
                          f"{', '.join(header)}")
    if "stamp_ns" in header:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        t = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(
            include_columns=["scan_id", "stamp_ns"], column_types={"scan_id": pa.int64(), "stamp_ns": pa.int64()}))
        return dict(zip(t["scan_id"].to_pylist(), t["stamp_ns"].to_pylist()))
    names = ["scan_id", "gps_seconds"] + (["gps_week"] if "gps_week" in header else [])
    cols = read_csv_columns(path, names)
    week = cols.get("gps_week")
    if week is None and default_week is not None:
        week = np.full(len(cols["scan_id"]), float(default_week))
    ns = stamps_ns(cols["gps_seconds"], week)
    return {int(i): int(t) for i, t in zip(cols["scan_id"], ns)}
