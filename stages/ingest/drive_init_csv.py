"""``cornermap drive init``: the CSV part of a draft: which CSV is GNSS/INS or wheel odometry, and its column
mapping from header names (synonyms, unit suffixes such as ``_deg`` / ``_m`` stripped, std aliases resolved)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

_SYNONYMS = {
    "time": ("gps_seconds", "gps_time", "seconds", "time_s", "time", "timestamp", "stamp", "t", "utc_time"),
    "week": ("gps_week", "week"),
    "lat": ("lat", "latitude", "lat_deg", "latitude_deg"),
    "lon": ("lon", "lng", "long", "longitude", "lon_deg", "longitude_deg"),
    "height": ("height", "alt", "altitude", "h", "height_m", "alt_m", "ellipsoidal_height"),
    "heading": ("azimuth", "heading", "yaw", "heading_deg", "yaw_rad"),
    "roll": ("roll", "roll_deg", "roll_rad"),
    "pitch": ("pitch", "pitch_deg", "pitch_rad"),
    "std_east": ("std_east", "east_std", "std_e", "sigma_east", "longitude_std"),
    "std_north": ("std_north", "north_std", "std_n", "sigma_north", "latitude_std"),
    "std_up": ("std_up", "up_std", "std_u", "sigma_up", "height_std"),
    "std_heading": ("std_heading", "azimuth_std", "heading_std", "std_yaw", "yaw_std"),
    "speed": ("speed", "speed_mps", "v", "vf", "velocity", "wheel_speed"),
    "yaw_rate": ("yaw_rate", "yaw_rate_radps", "gyro_z", "wz", "wu"),
}


_UNIT_SUFFIXES = ("_deg", "_rad", "_m", "_mps", "_radps", "_s", "_ns")
_STD_ALIASES = {"std_lat": "std_north", "std_lon": "std_east", "std_height": "std_up", "std_alt": "std_up",
                "std_azimuth": "std_heading", "lat_std": "std_north", "lon_std": "std_east"}


def _bare(name: str) -> str:
    """A column name without its unit suffix, std aliases resolved: ``std_lat_m`` -> ``std_north``."""
    low = name.strip().lower()
    for suffix in _UNIT_SUFFIXES:
        if low.endswith(suffix) and len(low) > len(suffix):
            low = low[: -len(suffix)]
            break
    return _STD_ALIASES.get(low, low)


def _pick(header: list[str], role: str) -> str | None:
    """The header column that plays ``role``: exact synonyms first, then synonyms after unit suffixes."""
    lower = {h.lower(): h for h in header}
    for name in _SYNONYMS[role]:
        if name in lower:
            return lower[name]
    bare = {_bare(h): h for h in header}
    for name in (role,) + _SYNONYMS[role]:
        if _bare(name) in bare:
            return bare[_bare(name)]
    return None


def _header(path: Path) -> list[str]:
    try:
        with open(path, newline="", errors="replace") as fh:
            return [c.strip() for c in next(csv.reader(fh), [])]
    except OSError:
        return []


def _column_values(path: Path, column: str, limit: int = 2000) -> np.ndarray:
    with open(path, newline="", errors="replace") as fh:
        reader = csv.DictReader(fh)
        out = []
        for n, row in enumerate(reader):
            if n >= limit:
                break
            try:
                out.append(float(row[column]))
            except (TypeError, ValueError, KeyError):
                continue
    return np.asarray(out, float)


def draft_csvs(folder: Path, d) -> None:
    """GNSS and odometry sections of the draft ``d`` (a ``drive_init.Draft``) from the folder's CSV files."""
    csvs = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".csv", ".txt") and p.name != "stamps.csv")
    gnss = odom = None
    for path in csvs:
        header = _header(path)
        if gnss is None and _pick(header, "lat") and _pick(header, "lon"):
            gnss = (path, header)
        elif odom is None and _pick(header, "speed") and _pick(header, "yaw_rate"):
            odom = (path, header)
    if gnss is None:
        d.add("# gnss: none found (a CSV with latitude/longitude columns); the map then has no geodetic frame")
    else:
        path, header = gnss
        rel = d.rel(path)
        pick = {role: _pick(header, role) for role in _SYNONYMS}
        d.add("gnss:")
        d.add(f"  file: {rel}", f"columns: {', '.join(header)}")
        if pick["time"]:
            t = _column_values(path, pick["time"])
            base = "unix" if t.size and np.nanmin(t) > 1e8 else "gps"
            week = f", week_column: {pick['week']}" if pick["week"] else ""
            note = "CHECK: unix seconds" if base == "unix" else \
                ("GPS week + seconds" if pick["week"] else "CHECK: GPS seconds without a week column")
            d.add(f"  time: {{column: {pick['time']}{week}, base: {base}}}", note)
        else:
            d.unknown("  time: {column: TIME, base: gps}", "no time column recognised")
        cols = {k: pick[k] for k in ("lat", "lon", "height", "heading", "roll", "pitch", "std_east", "std_north",
                                     "std_up", "std_heading") if pick[k]}
        d.add("  columns:")
        for key in ("lat", "lon", "height", "heading"):
            if key in cols:
                d.add(f"    {key}: {cols[key]}")
            else:
                d.unknown(f"    {key}: {key.upper()}", f"no {key} column recognised")
        for key in ("roll", "pitch", "std_east", "std_north", "std_up", "std_heading"):
            if key in cols:
                d.add(f"    {key}: {cols[key]}")
            else:
                d.add(f"    # {key}: none", "missing: " + ("no roll/pitch prior is used" if key in ("roll", "pitch")
                                                            else "the ingest param default is used (warned)"))
        heading = (cols.get("heading") or "").lower()
        unit_from_name = {_n.lower()[-4:] for _n in (cols.get(k) or "" for k in ("heading", "roll", "pitch"))}
        angles = [_column_values(path, cols[k]) for k in ("heading", "roll", "pitch") if k in cols]
        rad = bool(angles) and all(a.size == 0 or np.nanmax(np.abs(a)) <= 2 * np.pi + 0.01 for a in angles)
        if "_deg" in unit_from_name or "_rad" in unit_from_name:
            d.add(f"  angle_unit: {'rad' if '_rad' in unit_from_name else 'deg'}", "from the column names")
        else:
            d.add(f"  angle_unit: {'rad' if rad else 'deg'}", "CHECK: guessed from the values' range")
        d.add("  latlon_unit: deg", "CHECK")
        conv = "enu_yaw_ccw_from_east" if "yaw" in heading else "azimuth_cw_from_north"
        d.add(f"  heading_convention: {conv}", f"CHECK: guessed from the column name {cols.get('heading')!r} "
                                                "(azimuth/heading: clockwise from north; KITTI OXTS yaw: 0 = east, "
                                                "counter-clockwise)")
        d.add("  lever_arm_m: [0.0, 0.0, 0.0]", "CHECK: the GNSS/INS reference point in the vehicle frame")
    if odom is None:
        d.add("# odometry: none found (wheel speed + yaw rate CSV); evaluation then runs on ICP increments")
    else:
        path, header = odom
        pick = {role: _pick(header, role) for role in ("time", "week", "speed", "yaw_rate")}
        d.add("odometry:")
        d.add(f"  file: {d.rel(path)}")
        d.add(f"  time_column: {pick['time'] or 'TIME'}", "" if pick["time"] else "TODO: no time column recognised")
        if pick["week"]:
            d.add(f"  week_column: {pick['week']}")
        d.add(f"  speed: {pick['speed']}", "m/s")
        d.add(f"  yaw_rate: {pick['yaw_rate']}", "CHECK: rad/s, counter-clockwise positive")
