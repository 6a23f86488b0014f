"""``cornermap drive init FOLDER``: draft a drive file by inspecting a recorded drive's files.

What can be read off the files is filled in (scan folder and format, fields, point counts, a sensor guess from
the elevation histogram, the GNSS / odometry / stamps CSV column mapping, a survey cloud and its CRS); what cannot
(the lidar extrinsic, conventions a header does not state) is written with a ``# CHECK:`` comment, and what is
missing altogether with ``# TODO:``. The draft is meant to be read, completed and then checked with
``cornermap drive check``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.drive_init_csv import draft_csvs
from stages.ingest.scan_formats import read_scan
from stages.ingest.sensors import SENSORS, elevation_deg


@dataclass
class Draft:
    """The drive file being drafted: ordered YAML lines, and what could not be inferred. Paths are written relative
    to ``base``, the folder the drive file will be in (docs/drive-file.md); ``outside`` lists those that would
    leave its parent folder, which a drive file may not."""

    lines: list[str] = field(default_factory=list)
    todo: list[str] = field(default_factory=list)
    base: Path | None = None
    outside: list[str] = field(default_factory=list)

    def rel(self, path: Path) -> str:
        """``path`` as the drive file names it: relative to ``base``, '/'-separated."""
        path = Path(path).resolve()
        if self.base is None:
            return path.as_posix()
        text = Path(os.path.relpath(path, self.base)).as_posix()
        fence = str(self.base.parent)
        if os.path.commonpath([fence, str(path)]) != fence:
            self.outside.append(f"{text} ({path})")
        return text

    def add(self, text: str, note: str = "") -> None:
        self.lines.append(f"{text}  # {note}" if note else text)

    def unknown(self, text: str, what: str) -> None:
        self.todo.append(what)
        self.lines.append(f"{text}  # TODO: {what}")


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


def draft_drive_file(folder: Path, out: Path | None = None) -> Draft:
    """The draft of ``folder``'s drive file, to be written at ``out`` (default ``folder/drive.yaml``): its paths are
    relative to ``out``'s folder."""
    folder = Path(folder).resolve()
    d = Draft(base=Path(out).resolve().parent if out is not None else folder)
    d.add(f"# Drive file drafted by `cornermap drive init {folder.name}`: read every CHECK and TODO, then run "
          f"`cornermap drive check`.")
    d.add("# Keys, units and conventions: the comments below (the full contract: docs/drive-file.md in cornermap's "
          "source)")
    d.add(f"name: {folder.name}")
    fmt = _draft_scans(folder, d)
    d.add("scan_rate_hz: 10.0", "CHECK: the sensor's rotation rate")
    d.unknown("T_vehicle_lidar: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.7], [0, 0, 0, 1]]",
              "the lidar's pose in the vehicle frame (x forward, y left, z up; here: identity, 1.7 m up)")
    draft_csvs(folder, d)
    _draft_survey(folder, d, fmt)
    return d


def _draft_scans(folder: Path, d: Draft) -> str | None:
    """The scans, sensor and scan_times sections; returns the scan format (None: no sensor-frame scans)."""
    found = find_scan_folder(folder)
    if found is not None and found[1] == "las" and _georeferenced(found[2][0]):
        d.unknown("scans: {folder: scans, format: pcd}", f"{len(found[2])} LAS/LAZ files in "
                  f"{found[0].relative_to(folder).as_posix() or '.'} are georeferenced clouds (a survey), not "
                  f"sensor-frame scans; no scan folder found")
        found = None
    elif found is None:
        d.unknown("scans: {folder: scans, format: pcd}", "no folder with .pcd/.bin/.las scan files found")
    if found is None:
        d.unknown("sensor: generic", "sensor model")
        return None
    scan_dir, kind, files = found
    fmt = {"pcd": "pcd", "las": "las", "bin": bin_format(files[0])}[kind]
    sample = [files[0], files[len(files) // 2], files[-1]]
    elev, beams, n_points = [], [], []
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
    note = f"{len(files)} files; {min(n_points, default=0)}-{max(n_points, default=0)} points in 3 sampled"
    note += "; ring field present" if has_ring else ""
    note += "" if has_time else "; no per-point time (scans are not deskewed)"
    d.add("scans:")
    d.add(f"  folder: {d.rel(scan_dir)}", note)
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
        d.add(f"  file: {d.rel(stamps)}")
    elif numbered_us:
        d.add("scan_times: {source: filename_us}", "file names end in microsecond stamps")
    else:
        d.add("scan_times: {source: rate}", "CHECK: scan i at t0 + (i - first) / scan_rate_hz; t0 = first "
                                            "GNSS fix unless t0_s is given")
    return fmt


def _georeferenced(path: Path) -> bool:
    """A LAS/LAZ whose coordinates are far from its sensor (projected or geographic CRS, not a sensor frame)."""
    try:
        from stages.ingest.scan_formats import open_las_checked

        with open_las_checked(path) as reader:
            h = reader.header
            return bool(max(abs(h.mins[0]), abs(h.mins[1])) > 1000.0 or h.parse_crs() is not None)
    except Exception:  # noqa: BLE001 - treated as sensor-frame scans; check reports unreadable files
        return False


def _draft_survey(folder: Path, d: Draft, scan_format: str | None) -> None:
    if scan_format == "las":
        return
    clouds = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".las", ".laz"))
    if not clouds:
        return
    path = clouds[0]
    crs = None
    try:
        from stages.ingest.scan_formats import open_las_checked

        with open_las_checked(path) as reader:
            parsed = reader.header.parse_crs()
            crs = parsed.to_string() if parsed is not None else None
    except Exception:  # noqa: BLE001 - a draft notes it, check validates
        crs = None
    d.add("survey:")
    d.add(f"  file: {d.rel(path)}")
    if crs:
        d.add(f"  crs: \"{crs}\"", "from the LAS header")
    else:
        d.unknown("  crs: EPSG:XXXX", "the survey's CRS (not in its header), e.g. EPSG:28992 for RD New")
