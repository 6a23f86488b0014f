"""``cornermap drive init``: the GNSS/INS, odometry and prior-trajectory part of a draft.

Which CSV is GNSS/INS or wheel odometry, and its column mapping from header names: synonyms of the recorders users
bring (NovAtel INSPVA/INSPVAX exports, KITTI OXTS CSVs, ROS NavSatFix / IMU / Odometry exports flattened by
``rostopic echo -p`` (``field.latitude``, ``field.header.stamp`` in ns) or bag-to-CSV tools (``header.stamp.secs`` +
``.nsecs``), ``yaw_enu_rad``), unit suffixes (``_deg``, ``_rad``, ...) stripped and read as units, std aliases
resolved. KITTI's ``oxts/`` folder (``data/*.txt`` + ``timestamps.txt``) is read as it is published
(``format: kitti_oxts``). A TUM or KITTI poses file becomes a ``prior:`` section; a drive with neither GNSS nor a
prior gets a TODO naming what it lacks.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

_SYNONYMS = {
    "time": ("field.header.stamp", "header.stamp", "header.stamp.secs", "header.stamp.sec",  # the message's own
             "gps_seconds", "gps_time", "seconds", "time_s", "time", "timestamp", "stamp", "t", "utc_time",
             "gpstime", "%time"),  # before the recording's time (rostopic's %time, a bag CSV's Time)
    "nanosec": ("header.stamp.nsecs", "header.stamp.nanosec", "field.header.stamp.nsecs"),
    "week": ("gps_week", "week"),
    "lat": ("lat", "latitude", "lat_deg", "latitude_deg", "field.latitude"),
    "lon": ("lon", "lng", "long", "longitude", "lon_deg", "longitude_deg", "field.longitude"),
    "height": ("height", "alt", "altitude", "h", "height_m", "alt_m", "ellipsoidal_height", "field.altitude"),
    "heading": ("azimuth", "heading", "yaw", "heading_deg", "yaw_rad", "yaw_enu_rad", "yaw_enu", "azimuth_deg"),
    "roll": ("roll", "roll_deg", "roll_rad"),
    "pitch": ("pitch", "pitch_deg", "pitch_rad"),
    "std_east": ("std_east", "east_std", "std_e", "sigma_east", "longitude_std", "longitude_sigma",
                 "field.position_covariance0", "position_covariance0", "position_covariance.0"),
    "std_north": ("std_north", "north_std", "std_n", "sigma_north", "latitude_std", "latitude_sigma",
                  "field.position_covariance4", "position_covariance4", "position_covariance.4"),
    "std_up": ("std_up", "up_std", "std_u", "sigma_up", "height_std", "altitude_std", "height_sigma",
               "field.position_covariance8", "position_covariance8", "position_covariance.8"),
    "std_heading": ("std_heading", "azimuth_std", "heading_std", "std_yaw", "yaw_std", "azimuth_sigma"),
    "undulation": ("undulation", "undulation_m"),
    "speed": ("speed", "speed_mps", "v", "vf", "velocity", "wheel_speed", "field.twist.twist.linear.x",
              "twist.twist.linear.x"),
    "yaw_rate": ("yaw_rate", "yaw_rate_radps", "gyro_z", "wz", "wu", "field.angular_velocity.z",
                 "angular_velocity.z", "field.twist.twist.angular.z", "twist.twist.angular.z"),
}
_UNIT_SUFFIXES = ("_deg", "_rad", "_m", "_mps", "_radps", "_s", "_ns")
_STD_ALIASES = {"std_lat": "std_north", "std_lon": "std_east", "std_height": "std_up", "std_alt": "std_up",
                "std_azimuth": "std_heading", "lat_std": "std_north", "lon_std": "std_east"}
_PREFIXES = ("field.", "%")
_COVARIANCE = ("position_covariance",)
_HEADING_CONVENTION = {"azimuth_cw_from_north": "azimuth/heading: 0 = north, clockwise",
                       "enu_yaw_ccw_from_east": "ENU yaw: 0 = east, counter-clockwise"}


def _q(name: str) -> str:
    """A column name as a YAML flow scalar: plain when it can be, else double-quoted (``%time``, spaces)."""
    import json
    import re

    return name if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", name) else json.dumps(name)


def _bare(name: str) -> str:
    """A column name without its recorder prefix and unit suffix, std aliases resolved: ``std_lat_m`` ->
    ``std_north``, ``field.latitude`` -> ``latitude``."""
    low = name.strip().lower()
    for prefix in _PREFIXES:
        if low.startswith(prefix) and len(low) > len(prefix):
            low = low[len(prefix):]
    for suffix in _UNIT_SUFFIXES:
        if low.endswith(suffix) and len(low) > len(suffix):
            low = low[: -len(suffix)]
            break
    return _STD_ALIASES.get(low, low)


def _pick(header: list[str], role: str) -> str | None:
    """The header column that plays ``role``: exact synonyms first, then synonyms without prefix and unit suffix."""
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
    if Path(path).is_dir():  # a KITTI OXTS folder
        from stages.ingest.kitti_raw import read_oxts_columns

        try:
            return read_oxts_columns(path, [column])[column][:limit]
        except Exception:  # noqa: BLE001 - a draft notes it; check reports the folder's problem
            return np.zeros(0)
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


def _time_unit(values: np.ndarray) -> str:
    """s, ms, us or ns from the magnitude of epoch stamps (ROS writes integer ns: 1.7e18)."""
    top = float(np.nanmax(values)) if values.size else 0.0
    return "ns" if top > 1e17 else "us" if top > 1e14 else "ms" if top > 1e11 else "s"


def _find_tables(folder: Path) -> tuple[tuple[Path, list[str]] | None, tuple[Path, list[str]] | None]:
    """(GNSS table, odometry table) as (path, header): CSVs by their columns, KITTI's oxts/ folder for both."""
    from stages.ingest.kitti_raw import is_oxts_folder, oxts_header

    oxts = next((p for p in sorted(folder.rglob("oxts")) if p.is_dir() and is_oxts_folder(p)), None)
    if oxts is not None:
        header = oxts_header(oxts)
        return (oxts, header), (oxts, header)
    csvs = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".csv", ".txt") and p.name != "stamps.csv"
                  and p.is_file())
    gnss = odom = None
    for path in csvs:
        header = _header(path)
        if gnss is None and _pick(header, "lat") and _pick(header, "lon"):
            gnss = (path, header)
        if odom is None and _pick(header, "speed") and _pick(header, "yaw_rate"):
            odom = (path, header)
    return gnss, odom


def draft_csvs(folder: Path, d) -> bool:
    """GNSS and odometry sections of the draft ``d`` (a ``drive_init.Draft``); True when a GNSS table was found."""
    gnss, odom = _find_tables(folder)
    if gnss is None:
        d.add("# gnss: none found (no CSV with latitude/longitude columns, no KITTI oxts/ folder)")
    else:
        _draft_gnss(*gnss, d)
    if odom is None:
        d.add("# odometry: none found (wheel speed + yaw rate CSV); evaluation then runs on ICP increments")
    else:
        _draft_odometry(*odom, d)
    return gnss is not None


def _draft_gnss(path: Path, header: list[str], d) -> None:
    oxts = path.is_dir()
    pick = {role: _pick(header, role) for role in _SYNONYMS}
    if oxts:  # KITTI dataformat.txt: pos_accuracy is the north/east position accuracy (m)
        pick.update(std_east="pos_accuracy", std_north="pos_accuracy", std_up=None, std_heading=None, height="alt")
    d.add("gnss:")
    if oxts:
        n = len(list((path / "data").glob("*.txt")))
        d.add(f"  file: {d.rel(path)}", f"KITTI OXTS: {n} files in data/ with timestamps.txt")
        d.add("  format: kitti_oxts")
    else:
        d.add(f"  file: {d.rel(path)}", f"columns: {', '.join(header)}"[:300])
    if pick["time"]:
        t = _column_values(path, pick["time"])
        unit = _time_unit(t)
        t_s = t * {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}[unit]
        base = "unix" if t_s.size and np.nanmin(t_s) > 1e8 else "gps"
        extra = (f", week_column: {_q(pick['week'])}" if pick["week"] else "") + \
            (f", unit: {unit}" if unit != "s" else "") + \
            (f", nanosec_column: {_q(pick['nanosec'])}" if pick["nanosec"] else "")
        note = "timestamps.txt date-times, read as UTC: unix" if oxts else \
            ("CHECK: unix time" + (f" in {unit} (ROS stamps)" if unit != "s" else "") if base == "unix" else
             ("GPS week + seconds" if pick["week"] else "CHECK: GPS seconds without a week column"))
        d.add(f"  time: {{column: {_q(pick['time'])}{extra}, base: {base}}}", note)
    else:
        d.unknown("  time: {column: TIME, base: gps}", "no time column recognised")
    cols = {k: pick[k] for k in ("lat", "lon", "height", "heading", "roll", "pitch", "std_east", "std_north",
                                 "std_up", "std_heading", "undulation") if pick[k]}
    d.add("  columns:")
    for key in ("lat", "lon", "height", "heading"):
        if key in cols:
            note = "CHECK: KITTI's 'altitude'; the drive file wants the WGS84 ellipsoidal height" \
                if oxts and key == "height" else \
                ("INSPVAX: height above mean sea level; + undulation below = ellipsoidal" if key == "height" and
                 "undulation" in cols else "")
            d.add(f"    {key}: {_q(cols[key])}", note)
        elif key == "heading":
            imu = "; an IMU export's orientation quaternion is no heading column" if any(
                "orientation" in h for h in header) else ""
            d.unknown(f"    {key}: HEADING", f"no heading column recognised (NavSatFix has none{imu}): a column "
                                              "of the vehicle's heading")
        else:
            d.unknown(f"    {key}: {key.upper()}", f"no {key} column recognised")
    for key in ("roll", "pitch", "std_east", "std_north", "std_up", "std_heading", "undulation"):
        if key in cols:
            d.add(f"    {key}: {_q(cols[key])}")
        elif key != "undulation":
            d.add(f"    # {key}: none", "missing: " + ("no roll/pitch prior is used" if key in ("roll", "pitch")
                                                        else "the ingest param default is used (warned)"))
    if any(any(c in (cols.get(k) or "").lower() for c in _COVARIANCE) for k in ("std_east", "std_north", "std_up")):
        d.add("  std_is_variance: true", "ROS position_covariance: variances (m^2), diagonal 0/4/8 = east/north/up")
    angle_cols = [cols.get(k) or "" for k in ("heading", "roll", "pitch")]
    named = {n.lower()[-4:] for n in angle_cols}
    angles = [_column_values(path, cols[k]) for k in ("heading", "roll", "pitch") if k in cols]
    rad = bool(angles) and all(a.size == 0 or np.nanmax(np.abs(a)) <= 2 * np.pi + 0.01 for a in angles)
    if oxts:
        d.add("  angle_unit: rad", "KITTI dataformat.txt: roll, pitch, yaw in rad")
    elif "_deg" in named or "_rad" in named:
        d.add(f"  angle_unit: {'rad' if '_rad' in named else 'deg'}", "from the column names")
    else:
        d.add(f"  angle_unit: {'rad' if rad else 'deg'}", "CHECK: guessed from the values' range")
    d.add("  latlon_unit: deg", "CHECK")
    heading = (cols.get("heading") or "").lower()
    conv = "enu_yaw_ccw_from_east" if "yaw" in heading else "azimuth_cw_from_north"
    if oxts or "enu" in heading:
        why = "KITTI dataformat.txt: yaw 0 = east, counter-clockwise" if oxts else \
            f"the column name {cols.get('heading')!r} says ENU yaw"
    else:
        why = f"CHECK: guessed from the column name {cols.get('heading')!r} ({_HEADING_CONVENTION[conv]}; a 'yaw' " \
              "may be NED, clockwise from north)"
    d.add(f"  heading_convention: {conv}", why)
    d.add("  lever_arm_m: [0.0, 0.0, 0.0]", "the vehicle frame is the OXTS unit's" if oxts else
          "CHECK: the GNSS/INS reference point in the vehicle frame")


def _draft_odometry(path: Path, header: list[str], d) -> None:
    pick = {role: _pick(header, role) for role in ("time", "nanosec", "week", "speed", "yaw_rate")}
    if path.is_dir():  # KITTI dataformat.txt: wu is the rate about the upward axis (wz: the unit's own z)
        pick["yaw_rate"] = "wu"
    d.add("odometry:")
    d.add(f"  file: {d.rel(path)}", "the OXTS forward speed vf and yaw rate wu" if path.is_dir() else "")
    if path.is_dir():
        d.add("  format: kitti_oxts")
    d.add(f"  time_column: {_q(pick['time'] or 'TIME')}", "" if pick["time"] else "TODO: no time column recognised")
    if pick["time"] and not path.is_dir():
        unit = _time_unit(_column_values(path, pick["time"]))
        if unit != "s":
            d.add(f"  time_unit: {unit}")
    if pick["nanosec"]:
        d.add(f"  nanosec_column: {_q(pick['nanosec'])}")
    if pick["week"]:
        d.add(f"  week_column: {_q(pick['week'])}")
    d.add(f"  speed: {_q(pick['speed'])}", "m/s")
    d.add(f"  yaw_rate: {_q(pick['yaw_rate'])}", "CHECK: rad/s, counter-clockwise positive")


def _pose_file_kind(path: Path) -> tuple[str, int] | None:
    """('tum' | 'kitti', rows) when every non-comment line holds 8 or 12 numbers, else None."""
    try:
        if path.stat().st_size > 64 << 20:
            return None
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip() and not
                 ln.lstrip().startswith("#")]
        widths = {len(ln.replace(",", " ").split()) for ln in lines}
        if len(widths) != 1 or not lines:
            return None
        [float(v) for v in lines[0].replace(",", " ").split()]
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    width = widths.pop()
    return ({8: "tum", 12: "kitti"}[width], len(lines)) if width in (8, 12) else None


def draft_prior(folder: Path, d, has_gnss: bool) -> None:
    """A ``prior:`` section for a TUM / KITTI poses file in the folder; without GNSS, what fixes the drive's frame."""
    found = None
    for path in sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".txt", ".tum", ".csv") and p.is_file()):
        if path.parent.name == "data" or path.name in ("stamps.csv",):
            continue
        kind = _pose_file_kind(path)
        if kind is not None:
            found = (path, *kind)
            break
    if found is not None:
        path, fmt, n = found
        d.add("prior:", f"{n} poses ({fmt})")
        d.add(f"  file: {d.rel(path)}")
        d.add(f"  format: {fmt}")
        d.add("  frame: local", "CHECK: local (z up, origin and heading unknown: SLAM poses) or enu with origin: "
                                "{lat_deg, lon_deg, h_m}")
        d.add(f"  time: {'stamps' if fmt == 'tum' else 'scan_order'}",
              "CHECK: TUM t in the drive's time base; scan_order: row k = scan k" if fmt == "tum" else
              "KITTI poses: row k = scan k")
        d.add("  body: lidar", "CHECK: whose poses the file holds (lidar or vehicle)")
        d.add("  std_m: [0.1, 0.1, 0.1]", "CHECK: the poses' std per axis (m)")
        d.add("  std_deg: [0.1, 0.1, 0.5]", "CHECK: roll, pitch, yaw std (deg)")
    if has_gnss:
        return
    if found is None:
        d.todo.append("no GNSS and no prior trajectory: the drive cannot be placed in a map frame (add a gnss "
                      "section, prior: a TUM/KITTI poses file, or start: a heading at cornermap build --origin)")
        d.add("# TODO: no GNSS and no prior trajectory: nothing places this drive in a map frame; add one of: gnss "
              "(a GNSS/INS CSV or KITTI oxts/), prior (a TUM/KITTI poses file: docs/drive-file.md), or start (below)")
    d.add("# start: {heading_deg: 0.0, heading_convention: azimuth_cw_from_north, std_heading_deg: 2.0}",
          "the drive's first pose at the map's origin (cornermap build --origin): uncomment with its heading (it "
          "places the drive by itself, odometry and loops giving the rest, or aligns a local prior)")
    if found is not None:
        d.todo.append("the prior is in a local frame unless stated otherwise: uncomment start: with the drive's "
                      "initial heading, or give prior.frame: enu with its origin")
