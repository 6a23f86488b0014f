"""One pass over a drive's scan files: read, drop invalid points, assign rings, build Arrow pieces.

Memory is bounded by one piece (``PIECE_ROWS`` points) plus one scan, whatever the drive length.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from pipeline.errors import CornermapError, FormatError
from stages.ingest.drive_file import DriveSpec
from stages.ingest.scan_format_table import SCAN_SUFFIXES
from stages.ingest.scan_formats import ScanPoints, drop_invalid_points, read_scan
from stages.ingest.sensors import SENSORS, ring_coverage, rings_from_elevation_voted, rings_from_point_order

log = logging.getLogger(__name__)
PIECE_ROWS = 2_000_000


@dataclass(frozen=True)
class ScanFile:
    scan_id: int
    path: Path | None  # None: listed in the stamps file but missing on disk
    stamp_ns: int | None  # None: no stamp known


@dataclass(frozen=True)
class ScanResult:
    index_row: dict
    points: ScanPoints | None  # kept points (None when quarantined)
    ring: np.ndarray | None
    missing_rings: list[int]
    drops: dict[str, int]


def list_scan_files(folder: Path, fmt: str) -> list[Path]:
    """The folder's scan files by name; a symbolic link whose target is gone is listed too, so that it is read,
    quarantined ("No such file") and reported like any unreadable scan instead of silently skipped."""
    suffixes = SCAN_SUFFIXES[fmt]
    return sorted(p for p in folder.iterdir()
                  if (p.is_file() or (p.is_symlink() and not p.exists())) and p.name.lower().endswith(suffixes))


MAX_SCAN_ID = 100_000_000  # ten days at 100 Hz: anything larger is a broken file name or stamps row
_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def scan_numbers(files: list[Path]) -> list[int] | None:
    """The number in each file name (the last run of digits, e.g. ``0000000042.pcd`` -> 42), or None when a
    name carries no number, two files share one, or a number is out of range: ids then follow the listing."""
    numbers = []
    for p in files:
        stem = p.name.split(".")[0]
        match = _NUMBER.search(stem)
        if not match or len(match.group(1)) > 12:
            return None
        numbers.append(int(match.group(1)))
    if len(set(numbers)) != len(numbers) or any(n >= MAX_SCAN_ID for n in numbers):
        return None
    return numbers


def stamp_from_filename_us(path: Path) -> int:
    match = re.search(r"(\d{10,})(?:\.[A-Za-z]+)*$", path.name)
    if not match:
        raise FormatError(f"{path}: no microsecond time stamp at the end of the file name (scan_times "
                          f"source filename_us, e.g. '...__1532402927647951.pcd.bin')")
    return int(match.group(1)) * 1000


def elevation_table(spec: DriveSpec) -> tuple[float, ...]:
    """The drive's beam table: ``elevations_deg``, else the sensor's own ``calibration_file``, else the model's."""
    if spec.elevations_deg:
        return tuple(spec.elevations_deg)
    if spec.calibration_file:
        from stages.ingest.sensor_calibration import calibration_table

        return calibration_table(spec.path(spec.calibration_file))
    return SENSORS[spec.sensor].elevations_deg


def choose_ring_method(spec: DriveSpec, has_file_ring: bool) -> str:
    wanted = spec.scans.ring_from
    if wanted != "auto":
        return wanted
    if has_file_ring:
        return "file"
    table = elevation_table(spec)
    if spec.scans.format == "kitti_bin" or SENSORS[spec.sensor].ring_from_order or not table:
        return "point_order" if spec.scans.format in ("pcd", "kitti_bin") else "none"
    return "elevation_table"


def assign_rings(points: ScanPoints, spec: DriveSpec, vote_min_share: float) -> tuple[np.ndarray, str]:
    method = choose_ring_method(spec, points.ring is not None)
    if method == "file":
        if points.ring is None:
            raise FormatError("scans.ring_from is 'file' but the scan has no ring field")
        return points.ring, "file"
    if method == "elevation_table":
        ring, _ = rings_from_elevation_voted(points.x_m, points.y_m, points.z_m, elevation_table(spec),
                                             vote_min_share)
        return ring, "elevation_table"
    if method == "point_order":
        table = elevation_table(spec)
        return rings_from_point_order(points.x_m, points.y_m, points.z_m,
                                      elevations_deg=table or None), "point_order"
    return np.full(len(points), -1, np.int16), "none"


def process_scan(scan: ScanFile, spec: DriveSpec, chunk: int, min_range_m: float, vote_min_share: float
                 ) -> ScanResult:
    rel = "" if scan.path is None else str(scan.path.relative_to(spec.drive_dir)
                                           if scan.path.is_relative_to(spec.drive_dir) else scan.path)
    row = {"scan_id": scan.scan_id, "stamp_ns": scan.stamp_ns if scan.stamp_ns is not None else -1,
           "source_file": rel, "n_points": 0, "n_dropped_nonfinite": 0, "n_dropped_zero": 0, "rings_present": 0,
           "ring_source": "", "status": "quarantined", "reason": None, "chunk": chunk}
    if scan.path is None:
        return ScanResult({**row, "reason": "file listed in the scan stamps is missing"}, None, None, [], {})
    if scan.stamp_ns is None:
        return ScanResult({**row, "reason": "no time stamp for this scan in the stamps file"}, None, None, [], {})
    try:
        raw = read_scan(scan.path, spec.scans.format)
        points, drops = drop_invalid_points(raw, min_range_m)
        if len(points) == 0:
            raise FormatError(f"{scan.path}: no valid points ({len(raw)} in the file: {drops['nonfinite']} non-finite, "
                              f"{drops['zero']} at (0,0,0), {drops['near']} nearer than {min_range_m} m)")
        ring, source = assign_rings(points, spec, vote_min_share)
    except (CornermapError, OSError, ValueError, MemoryError) as exc:  # a per-file problem: quarantine this file
        reason = (
            str(exc) if isinstance(exc, CornermapError) else f"{scan.path}: unreadable ({type(exc).__name__}: {exc})"
        )
        log.warning("quarantined %s: %s", scan.path, reason)
        return ScanResult({**row, "reason": reason}, None, None, [], {})
    n_rings = len(elevation_table(spec)) or (int(ring.max()) + 1 if len(ring) and source != "none" else 0)
    present, missing = ring_coverage(ring, n_rings)
    row.update(n_points=len(points), n_dropped_nonfinite=drops["nonfinite"], n_dropped_zero=drops["zero"],
               rings_present=present, ring_source=source, status="ok")
    return ScanResult(row, points, ring, missing, drops)


def points_table(drive: str, chunk: int, results: list[ScanResult]):
    from stages.common.records import RawScanPoints, encode_scans_raw

    ok = [r for r in results if r.points is not None]
    n = [len(r.points) for r in ok]
    total = int(sum(n))

    def cat(get, dtype) -> np.ndarray:
        return np.concatenate([get(r) for r in ok]).astype(dtype, copy=False) if ok else np.zeros(0, dtype)

    xyz = np.empty((total, 3), np.float32, order="F")  # column-major: each coordinate one contiguous column
    for j, c in enumerate(("x_m", "y_m", "z_m")):
        xyz[:, j] = cat(lambda r: getattr(r.points, c), np.float32)
    zeros = lambda r: np.zeros(len(r.points), np.float32)  # noqa: E731
    points = RawScanPoints(
        scan_id=np.repeat([r.index_row["scan_id"] for r in ok], n).astype(np.int64),
        stamp_ns=np.repeat([r.index_row["stamp_ns"] for r in ok], n).astype(np.int64),
        xyz_lidar_m=xyz, intensity=cat(lambda r: r.points.intensity, np.float32), ring=cat(lambda r: r.ring, np.int16),
        time_offset_s=cat(lambda r: r.points.time_offset_s if r.points.time_offset_s is not None else zeros(r),
                          np.float32))
    return encode_scans_raw(drive, chunk, points)


def iter_scan_results(scans: list[ScanFile], spec: DriveSpec, chunk_size: int, min_range_m: float,
                      vote_min_share: float) -> Iterator[ScanResult]:
    for scan in scans:
        yield process_scan(scan, spec, scan.scan_id // chunk_size, min_range_m, vote_min_share)
