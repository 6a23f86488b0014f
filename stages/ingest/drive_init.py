"""``cornermap drive init FOLDER``: draft a drive file by inspecting a recorded drive's files.

What can be read off the files is filled in (scan folder and format, fields, point counts, a sensor guess from
the elevation histogram, the GNSS / odometry / stamps CSV column mapping, a survey cloud and its CRS); what cannot
(the lidar extrinsic, conventions a header does not state) is written with a ``# CHECK:`` comment, and what is
missing altogether with ``# TODO:``. The draft is meant to be read, completed and then checked with
``cornermap drive check``.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.scan_formats import read_scan
from stages.ingest.sensors import SENSORS, elevation_deg

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


@dataclass
class Draft:
    """The drive file being drafted: ordered YAML lines, and what could not be inferred."""

    lines: list[str] = field(default_factory=list)
    todo: list[str] = field(default_factory=list)

    def add(self, text: str, note: str = "") -> None:
        self.lines.append(f"{text}  # {note}" if note else text)

    def unknown(self, text: str, what: str) -> None:
        self.todo.append(what)
        self.lines.append(f"{text}  # TODO: {what}")


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


def find_scan_folder(folder: Path) -> tuple[Path, str, list[Path]] | None:
    """The folder (the drive folder or a sub-folder) holding the most scan files, its format and files."""
    best = None
    for d in [folder] + sorted(p for p in folder.rglob("*") if p.is_dir()):
        for fmt, suffixes in (("pcd", (".pcd",)), ("bin", (".bin",)), ("las", (".las", ".laz"))):
            files = sorted(p for p in d.iterdir() if p.is_file() and p.name.lower().endswith(suffixes))
            if files and (best is None or len(files) > len(best[2])):
                best = (d, fmt, files)
    return best


def bin_format(path: Path) -> str:
    """kitti_bin (x y z reflectance) or nuscenes_bin (x y z intensity ring), from the record layout."""
    size = path.stat().st_size
    if size % 20 == 0 and size % 16 != 0:
        return "nuscenes_bin"
    if size % 20 == 0:
        a = np.fromfile(path, "<f4", count=min(size // 4, 20 * 5000)).reshape(-1, 5)
        ring = a[:, 4]
        if np.all(np.isfinite(ring)) and np.all(ring == np.floor(ring)) and ring.min() >= 0 and ring.max() < 256:
            return "nuscenes_bin"
    return "kitti_bin"


def guess_sensor(elev_deg: np.ndarray, n_beams: int | None) -> tuple[str, str]:
    """The sensor with ``n_beams`` beams (from a ring field or the point order) whose table best spans the
    scan's elevations (0.5th-99.5th percentile; the lowest beams often miss), and why; else the best span."""
    lo, hi = np.percentile(elev_deg, [0.5, 99.5])
    scores = []
    for name, model in SENSORS.items():
        if not model.elevations_deg:
            continue
        t = model.elevations_deg
        mismatch = 0.0 if n_beams is None or n_beams == len(t) else 100.0
        scores.append((mismatch + abs(t[-1] - hi) + 0.5 * abs(t[0] - lo), name))
    err, name = min(scores)
    table = SENSORS[name].elevations_deg
    why = f"{n_beams or 'unknown'} beams, elevations {lo:.1f}..{hi:.1f} deg; {name} has {len(table)} beams over " \
          f"{table[0]:.1f}..{table[-1]:.1f}"
    # The top beam is reliable (it hits facades); the lowest often see the car itself or nothing.
    same_count = n_beams is not None and n_beams == len(table)
    ok = abs(table[-1] - hi) < 3.0 if same_count else err < 6.0
    return (name if ok else "generic"), why


def count_beams(points) -> int | None:
    """Beams in one scan: the ring field's range, else the number of laser lines in point order (KITTI-style
    exports), when that is a plausible beam count."""
    from stages.ingest.sensors import rings_from_point_order

    if points.ring is not None and len(points.ring):
        return int(points.ring.max()) + 1
    lines = rings_from_point_order(points.x_m, points.y_m, points.z_m)
    n = int(lines.max()) + 1 if len(lines) else 0
    return n if n in (16, 32, 64, 128) else None


def draft_drive_file(folder: Path) -> Draft:
    folder = Path(folder).resolve()
    d = Draft()
    d.add(f"# Drive file drafted by `cornermap drive init {folder.name}`: read every CHECK and TODO, then run "
          f"`cornermap drive check`.")
    d.add("# Keys, units and conventions: docs/drive-file.md")
    d.add(f"name: {folder.name}")
    found = find_scan_folder(folder)
    n_points = []
    if found is None:
        d.unknown("scans: {folder: scans, format: pcd}", "no folder with .pcd/.bin/.las scan files found")
        d.unknown("sensor: generic", "sensor model")
        fmt = None
    else:
        scan_dir, kind, files = found
        fmt = {"pcd": "pcd", "las": "las", "bin": bin_format(files[0])}[kind]
        if fmt == "las" and _georeferenced(files[0]):
            d.unknown("scans: {folder: scans, format: pcd}", f"{len(files)} LAS/LAZ files in "
                      f"{scan_dir.relative_to(folder).as_posix() or '.'} are georeferenced clouds (a survey), not "
                      f"sensor-frame scans; no scan folder found")
            d.unknown("sensor: generic", "sensor model")
            d.add("scan_rate_hz: 10.0", "CHECK: the sensor's rotation rate")
            d.unknown("T_vehicle_lidar: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.7], [0, 0, 0, 1]]",
                      "the lidar's pose in the vehicle frame")
            _draft_csvs(folder, d)
            _draft_survey(folder, d, None)
            return d
        sample = [files[0], files[len(files) // 2], files[-1]]
        elev, beams = [], []
        has_ring = has_time = False
        for f in sample:
            try:
                pts = read_scan(f, fmt)
            except Exception:  # noqa: BLE001 - a draft notes unreadable samples, check reports them
                continue
            ok = np.isfinite(pts.x_m) & (np.abs(pts.x_m) + np.abs(pts.y_m) + np.abs(pts.z_m) > 0)
            n_points.append(int(ok.sum()))
            elev.append(elevation_deg(pts.x_m[ok], pts.y_m[ok], pts.z_m[ok]))
            beams.append(count_beams(pts.select(ok)))
            has_ring |= pts.ring is not None
            has_time |= pts.time_offset_s is not None
        rel = scan_dir.relative_to(folder).as_posix() or "."
        note = f"{len(files)} files; {min(n_points, default=0)}-{max(n_points, default=0)} points in 3 sampled"
        if has_ring:
            note += "; ring field present"
        if not has_time:
            note += "; no per-point time (scans are not deskewed)"
        d.add("scans:")
        d.add(f"  folder: {rel}", note)
        d.add(f"  format: {fmt}")
        if elev:
            known = [b for b in beams if b]
            sensor, why = guess_sensor(np.concatenate(elev), max(known) if known else None)
            d.add(f"sensor: {sensor}", f"CHECK: guessed from the elevation histogram ({why})")
            if sensor == "generic":
                d.unknown("# elevations_deg: [...]", "the beam elevation table (ascending) if rings are to be "
                                                     "recovered from elevation")
        else:
            d.unknown("sensor: generic", "no sampled scan was readable")
        stamps = scan_dir / "stamps.csv"
        numbered_us = all(len("".join(ch for ch in f.name.split(".")[0] if ch.isdigit())) >= 13 for f in sample)
        if stamps.is_file():
            d.add("scan_times:", "scan stamps from the stamps file")
            d.add(f"  source: {'pcd_field' if has_time else 'stamps_csv'}")
            d.add(f"  file: {stamps.relative_to(folder).as_posix()}")
        elif numbered_us:
            d.add("scan_times: {source: filename_us}", "file names end in microsecond stamps")
        else:
            d.add("scan_times: {source: rate}", "CHECK: scan i at t0 + (i - first) / scan_rate_hz; t0 = first "
                                                "GNSS fix unless t0_s is given")
    d.add("scan_rate_hz: 10.0", "CHECK: the sensor's rotation rate")
    d.unknown("T_vehicle_lidar: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.7], [0, 0, 0, 1]]",
              "the lidar's pose in the vehicle frame (x forward, y left, z up; here: identity, 1.7 m up)")
    _draft_csvs(folder, d)
    _draft_survey(folder, d, fmt)
    return d


def _georeferenced(path: Path) -> bool:
    """A LAS/LAZ whose coordinates are far from its sensor (projected or geographic CRS, not a sensor frame)."""
    try:
        import laspy

        with laspy.open(path) as reader:
            h = reader.header
            return bool(max(abs(h.mins[0]), abs(h.mins[1])) > 1000.0 or h.parse_crs() is not None)
    except Exception:  # noqa: BLE001 - treated as sensor-frame scans; check reports unreadable files
        return False


def _draft_csvs(folder: Path, d: Draft) -> None:
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
        rel = path.relative_to(folder).as_posix()
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
        d.add(f"  file: {path.relative_to(folder).as_posix()}")
        d.add(f"  time_column: {pick['time'] or 'TIME'}", "" if pick["time"] else "TODO: no time column recognised")
        if pick["week"]:
            d.add(f"  week_column: {pick['week']}")
        d.add(f"  speed: {pick['speed']}", "m/s")
        d.add(f"  yaw_rate: {pick['yaw_rate']}", "CHECK: rad/s, counter-clockwise positive")


def _draft_survey(folder: Path, d: Draft, scan_format: str | None) -> None:
    if scan_format == "las":
        return
    clouds = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".las", ".laz"))
    if not clouds:
        return
    path = clouds[0]
    crs = None
    try:
        import laspy

        with laspy.open(path) as reader:
            parsed = reader.header.parse_crs()
            crs = parsed.to_string() if parsed is not None else None
    except Exception:  # noqa: BLE001 - a draft notes it, check validates
        crs = None
    d.add("survey:")
    d.add(f"  file: {path.relative_to(folder).as_posix()}")
    if crs:
        d.add(f"  crs: \"{crs}\"", "from the LAS header")
    else:
        d.unknown("  crs: EPSG:XXXX", "the survey's CRS (not in its header), e.g. EPSG:28992 for RD New")
