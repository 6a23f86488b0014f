"""``cornermap drive init FOLDER``: draft a drive file by inspecting a recorded drive's files.

What can be read off the files is filled in (scan folder and format, fields, point counts, the sensor from a
calibration file or the scans (``drive_init_sensor``), stamps, the GNSS / odometry columns of CSVs and of KITTI's
OXTS folder, KITTI's ``calib_imu_to_velo.txt``, a prior trajectory, a survey cloud and its CRS); what cannot
(the lidar extrinsic, conventions a header does not state) is written with a ``# CHECK:`` comment, and what is
missing altogether with ``# TODO:``. The draft is meant to be read, completed and then checked with
``cornermap drive check``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.drive_init_csv import draft_csvs, draft_prior
from stages.ingest.drive_init_sensor import collect_evidence, find_calibration, guess_sensor
from stages.ingest.scan_format_table import suffix_groups, suffixes_help
from stages.ingest.scan_formats import read_scan


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
        """``path`` as the drive file names it: relative to ``base``, '/'-separated (lexically: a symbolic link
        placed in the drive's folder stays a path inside it, as the drive file's check reads it)."""
        path = Path(os.path.abspath(path))
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


def find_scan_folder(folder: Path) -> tuple[Path, tuple[str, ...], list[Path]] | None:
    """The folder (the drive folder or a sub-folder) holding the most scan files, the formats their suffix may be
    (the scan format table's group: ``.bin`` is kitti_bin or nuscenes_bin) and the files."""
    best = None
    for d in [folder] + sorted(p for p in folder.rglob("*") if p.is_dir()):
        for suffixes, formats in suffix_groups():
            files = sorted(p for p in d.iterdir() if p.is_file() and p.name.lower().endswith(suffixes))
            if files and (best is None or len(files) > len(best[2])):
                best = (d, formats, files)
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
    _draft_extrinsic(folder, d)
    gnss = draft_csvs(folder, d)
    draft_prior(folder, d, has_gnss=gnss)
    _draft_survey(folder, d, fmt)
    return d


def _draft_scans(folder: Path, d: Draft) -> str | None:
    """The scans, sensor and scan_times sections; returns the scan format (None: no sensor-frame scans)."""
    found = find_scan_folder(folder)
    if found is not None and found[1] == ("las",) and _georeferenced(found[2][0]):
        d.unknown("scans: {folder: scans, format: pcd}", f"{len(found[2])} LAS/LAZ files in "
                  f"{found[0].relative_to(folder).as_posix() or '.'} are georeferenced clouds (a survey), not "
                  f"sensor-frame scans; no scan folder found")
        found = None
    elif found is None:
        d.unknown("scans: {folder: scans, format: pcd}", f"no folder with {suffixes_help()} scan files found")
    if found is None:
        d.unknown("sensor: generic", "sensor model")
        return None
    scan_dir, formats, files = found
    fmt = formats[0] if len(formats) == 1 else bin_format(files[0])
    sample = [files[0], files[len(files) // 2], files[-1]]
    ev = collect_evidence(sample, fmt)
    has_ring = has_time = False
    for f in sample[:1]:
        try:
            pts = read_scan(f, fmt)
            has_ring, has_time = pts.ring is not None, pts.time_offset_s is not None
        except Exception:  # noqa: BLE001 - a draft notes unreadable samples, check reports them
            pass
    counts = ev.points_per_scan
    note = f"{len(files)} files; {min(counts, default=0)}-{max(counts, default=0)} points in 3 sampled"
    note += "; ring field present" if has_ring else ""
    note += "" if has_time else "; no per-point time (scans are not deskewed)"
    d.add("scans:")
    d.add(f"  folder: {d.rel(scan_dir)}", note)
    d.add(f"  format: {fmt}")
    calibration = find_calibration(folder)
    if calibration is not None:
        path, cal = calibration
        sensor = cal.model or "generic"
        d.add(f"sensor: {sensor}", f"from {path.name}: {cal.why}")
        d.add(f"calibration_file: {d.rel(path)}", f"the unit's own {len(cal.elevations_deg)}-beam table ({cal.kind})")
    elif counts:
        sensor, why = guess_sensor(ev)
        d.add(f"sensor: {sensor}", f"CHECK: guessed from the scans ({why})")
        if sensor == "generic":
            d.unknown("# elevations_deg: [...]", "the beam elevation table (ascending) or calibration_file, if rings "
                                                 "are to be recovered from elevation")
    else:
        d.unknown("sensor: generic", "no sampled scan was readable")
    _draft_scan_times(scan_dir, sample, has_time, d)
    return fmt


STAMP_LINE_FILES = ("timestamps_start.txt", "timestamps.txt", "times.txt", "stamps.txt")


def _draft_scan_times(scan_dir: Path, sample: list[Path], has_time: bool, d: Draft) -> None:
    """scan_times: a stamps CSV, a file of one stamp per line beside the scans (KITTI ``timestamps_start.txt``: the
    sweep's start, the scan stamp's meaning), stamps in the file names, else the rate."""
    from stages.ingest.kitti_raw import parse_stamp

    stamps = scan_dir / "stamps.csv"
    numbered_us = all(len("".join(ch for ch in f.name.split(".")[0] if ch.isdigit())) >= 13 for f in sample)
    lines = None
    for name in STAMP_LINE_FILES:
        for where in (scan_dir, scan_dir.parent):
            candidate = where / name
            try:
                first = candidate.read_text(encoding="utf-8", errors="strict").splitlines()[:1] \
                    if candidate.is_file() else []
                if lines is None and first and parse_stamp(first[0]) >= 0:
                    lines = candidate
            except (OSError, UnicodeDecodeError, ValueError):
                continue
    if stamps.is_file():
        d.add("scan_times:", "scan stamps from the stamps file")
        d.add(f"  source: {'pcd_field' if has_time else 'stamps_csv'}")
        d.add(f"  file: {d.rel(stamps)}")
    elif lines is not None:
        d.add("scan_times:", "one stamp per line, line k = scan k (date-times are read as UTC: unix base)")
        d.add("  source: stamps_lines")
        d.add(f"  file: {d.rel(lines)}")
    elif numbered_us:
        d.add("scan_times: {source: filename_us}", "file names end in microsecond stamps")
    else:
        d.add("scan_times: {source: rate}", "CHECK: scan i at t0 + (i - first) / scan_rate_hz; t0 = first "
                                            "GNSS fix unless t0_s is given")


def _draft_extrinsic(folder: Path, d: Draft) -> None:
    """T_vehicle_lidar from KITTI's ``calib_imu_to_velo.txt`` in the drive's folder or the date folder above it
    (the vehicle frame is then the OXTS unit's, whose poses the GNSS/INS reports), else a TODO."""
    from pipeline.errors import FormatError
    from stages.ingest.kitti_raw import vehicle_from_imu_calibration

    for where in (folder, folder.parent):
        calib = where / "calib_imu_to_velo.txt"
        if not calib.is_file():
            continue
        try:
            T = vehicle_from_imu_calibration(calib)
        except FormatError as exc:
            d.unknown("T_vehicle_lidar: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.7], [0, 0, 0, 1]]", str(exc))
            return
        U, _, Vt = np.linalg.svd(T[:3, :3])  # the file's 7 digits: the nearest rotation
        T[:3, :3] = U @ Vt
        rows = ", ".join("[" + ", ".join(f"{v:.9f}".rstrip("0").rstrip(".") if v else "0" for v in r) + "]"
                         for r in T)
        d.add(f"T_vehicle_lidar: [{rows}]", f"{calib.name} inverted: the vehicle frame is the OXTS unit's "
                                             "(x forward, y left, z up)")
        return
    d.unknown("T_vehicle_lidar: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.7], [0, 0, 0, 1]]",
              "the lidar's pose in the vehicle frame (x forward, y left, z up; here: identity, 1.7 m up)")


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
