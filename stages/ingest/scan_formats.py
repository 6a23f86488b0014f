"""Scan file formats -> ``ScanPoints`` (float32 x/y/z in the sensor frame, intensity, optional ring and time).

Formats: the table of ``scan_format_table.py`` (PCD v0.7, see ``pcd.py``; KITTI ``.bin``; nuScenes-style ``.bin``;
LAS/LAZ via laspy), each row naming its reader here. Every malformed file raises ``FormatError`` naming it.
"""
from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError
from stages.ingest.pcd import MAX_POINTS, PcdCloud, read_pcd
from stages.ingest.scan_format_table import SCAN_FORMAT_NAMES, scan_format

_INTENSITY = ("intensity", "reflectance", "i")
_RING = ("ring", "ring_index", "laser_id", "line")
_TIME = ("time", "time_offset", "timestamp", "t", "offset_time")  # float: seconds; integer: nanoseconds


@dataclass(frozen=True)
class ScanPoints:
    x_m: np.ndarray  # float32, sensor frame
    y_m: np.ndarray
    z_m: np.ndarray
    intensity: np.ndarray  # float32, raw as recorded
    ring: np.ndarray | None  # int16 from the file, or None
    time_offset_s: np.ndarray | None  # float32 seconds since scan start, or None
    time_unused: str | None = None  # why the file's per-point times were not used (``relative_time_s``), or None

    def __len__(self) -> int:
        return len(self.x_m)

    def select(self, mask: np.ndarray) -> "ScanPoints":
        return ScanPoints(self.x_m[mask], self.y_m[mask], self.z_m[mask], self.intensity[mask],
                          None if self.ring is None else self.ring[mask],
                          None if self.time_offset_s is None else self.time_offset_s[mask], self.time_unused)


def _first(columns: dict[str, np.ndarray], names: tuple[str, ...]) -> tuple[str, np.ndarray] | tuple[None, None]:
    for name in names:
        if name in columns:
            col = columns[name]
            return name, (col[:, 0] if col.ndim > 1 else col)
    return None, None


def _rings_checked(values: np.ndarray, source: str, field: str) -> np.ndarray:
    finite = np.isfinite(values) if values.dtype.kind == "f" else np.ones(len(values), bool)
    ok = finite & (values >= 0) & (values <= 1023)
    if values.dtype.kind == "f":
        ok &= np.floor(np.where(finite, values, 0)) == np.where(finite, values, 0)
    if not np.all(ok):
        bad = int(np.flatnonzero(~ok)[0])
        raise FormatError(f"{source}: {field} of point {bad} is {values[bad]!r}, expected an integer ring 0..1023 "
                          f"({int((~ok).sum())} bad points). Hint: the column order is not x y z intensity ring")
    return values.astype(np.int16)


MAX_TIME_OFFSET_S = 10.0  # a sweep lasts 0.05-1 s: a point time further from the scan's first is no time within it


def relative_time_s(values: np.ndarray, field: str) -> tuple[np.ndarray | None, str | None]:
    """Per-point times -> (float32 seconds since the scan's first point, None), or (None, why) when they are no times
    within one sweep. Float values are seconds, integers nanoseconds; absolute times (e.g. GPS seconds) are made
    relative to the earliest. A non-finite time stays NaN (``drop_invalid_points`` drops its point). When a finite time
    lies further than ``MAX_TIME_OFFSET_S`` from the scan start the times are not used, and the reason names the
    field, the first such point and its offset: a mobile-mapping tile read as one scan spans hours (the Amsterdam LAZ
    sample: 25 h), microseconds written as float seconds span 1e5 s, and a broken field (a fuzzed LAS file: 1e233 s,
    which overflowed float32 to inf) would have deskewed the points by kilometres. The points themselves are kept."""
    t = values.astype(np.float64) * (1e-9 if values.dtype.kind in "iu" else 1.0)
    if not t.size:
        return t.astype(np.float32), None
    lo, hi = float(t.min()), float(t.max())  # NaN when a time is NaN: two reductions in the common case
    if not (np.isfinite(lo) and np.isfinite(hi)):  # a time is not finite: NaN, and the bounds of the finite ones
        finite = np.isfinite(t)
        t = np.where(finite, t, np.nan)
        lo, hi = (float(t[finite].min()), float(t[finite].max())) if finite.any() else (0.0, 0.0)
    if lo > 1e5:  # absolute times (e.g. GPS seconds): relative to the first
        t -= lo
        lo, hi = 0.0, hi - lo
    if max(-lo, hi) > MAX_TIME_OFFSET_S:
        wild = np.abs(t) > MAX_TIME_OFFSET_S  # False for NaN
        bad = int(np.flatnonzero(wild)[0])
        return None, (f"{field} of point {bad} lies {t[bad]:.6g} s from the scan start ({int(wild.sum())} points "
                      f"beyond +-{MAX_TIME_OFFSET_S:g} s): no times within one sweep (another unit, a tile of many "
                      "passes, or a broken field), so the scan is not deskewed")
    return t.astype(np.float32), None


def points_from_pcd(cloud: PcdCloud, source: str = "<pcd>") -> ScanPoints:
    cols = cloud.columns
    missing = [c for c in ("x", "y", "z") if c not in cols]
    if missing:
        raise FormatError(f"{source}: PCD fields {' '.join(cloud.header.fields)} lack {', '.join(missing)}")
    multi = [c for c in ("x", "y", "z") if cols[c].ndim > 1]
    if multi:
        raise FormatError(f"{source}: PCD field(s) {', '.join(multi)} have COUNT > 1; expected one value per point")
    n = cloud.header.points
    _, intensity = _first(cols, _INTENSITY)
    ring_name, ring = _first(cols, _RING)
    time_name, time = _first(cols, _TIME)
    return ScanPoints(cols["x"].astype(np.float32), cols["y"].astype(np.float32), cols["z"].astype(np.float32),
                      np.zeros(n, np.float32) if intensity is None else intensity.astype(np.float32),
                      None if ring is None else _rings_checked(ring, source, ring_name),
                      *((None, None) if time is None else relative_time_s(time, time_name)))


def _read_float32_records(path: Path, width: int, what: str) -> np.ndarray:
    record = 4 * width
    try:
        size = path.stat().st_size
        if size > MAX_POINTS * record:
            raise FormatError(f"{path}: {size} bytes = more than the limit of {MAX_POINTS} {what} points per scan")
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read {what} scan: {exc.strerror or exc}") from exc
    if len(raw) % record:
        raise FormatError(f"{path}: {len(raw)} bytes is not a whole number of {record}-byte {what} records "
                          f"(record {len(raw) // record} is incomplete). Hint: truncated file, or the wrong "
                          f"format (kitti_bin has 4 float32 columns, nuscenes_bin 5)")
    return np.frombuffer(raw, "<f4").reshape(-1, width)


def read_kitti_bin(path: Path) -> ScanPoints:
    a = _read_float32_records(path, 4, "kitti_bin")
    return ScanPoints(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy(), a[:, 3].copy(), None, None)


def read_nuscenes_bin(path: Path) -> ScanPoints:
    a = _read_float32_records(path, 5, "nuscenes_bin")
    return ScanPoints(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy(), a[:, 3].copy(),
                      _rings_checked(a[:, 4], str(path), "column 5 (ring)"), None)


VLR_HEADER_BYTES, EVLR_HEADER_BYTES = 54, 60  # ASPRS LAS 1.4 s.2.5 and s.2.6


LAS_HEADER_MAX_BYTES = 375  # the LAS 1.4 public header block; earlier versions' are shorter


def check_las_record_counts(path: Path, head: bytes, size: int) -> None:
    """The header's (extended) variable-length record counts against the file size, before laspy reads them.

    ``head``: the file's first bytes (at least ``LAS_HEADER_MAX_BYTES`` when the file is that long), ``size``: its
    length. laspy reads as many records as the header announces: from an in-memory stream a corrupt count (4
    billion) made it build empty records until 18 GB were resident (found by tests/test_fuzz_inputs.py); from a
    file, 4 billion took 65 s and 2.4 GB before the points. Offsets from ASPRS LAS 1.4, table 3; a file too short
    for a header is left to laspy, which names it."""
    if len(head) < 104 or head[:4] != b"LASF":
        return
    header_size, = struct.unpack_from("<H", head, 94)
    n_vlrs, = struct.unpack_from("<I", head, 100)
    if header_size + n_vlrs * VLR_HEADER_BYTES > size:
        raise FormatError(f"{path}: header announces {n_vlrs} variable-length records after a {header_size}-byte "
                          f"header, but the file has {size} bytes. Hint: corrupt header")
    if head[25] >= 4 and header_size >= 247 and len(head) >= 247:
        start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and start + n_evlrs * EVLR_HEADER_BYTES > size:
            raise FormatError(f"{path}: header announces {n_evlrs} extended variable-length records from byte "
                              f"{start}, but the file has {size} bytes. Hint: truncated file or a corrupt header")


def open_las_checked(path: Path):  # noqa: ANN201 - a laspy.LasReader
    """``laspy.open(path)`` after the header's record counts were checked against the file's size (a large survey
    is streamed from the file, never read whole)."""
    import laspy

    path = Path(path)
    with open(path, "rb") as fh:
        check_las_record_counts(path, fh.read(LAS_HEADER_MAX_BYTES), path.stat().st_size)
    return laspy.open(path)


def _check_las_sizes(path: Path, size: int, reader) -> None:  # noqa: ANN001 - a laspy.LasReader
    """Declared point count and record size against the file size, before laspy allocates the points."""
    with reader as fh:
        h = fh.header
        count, record, offset = int(h.point_count), int(h.point_format.size), int(h.offset_to_point_data)
        compressed = bool(getattr(h, "are_points_compressed", False))
    if count > MAX_POINTS:
        raise FormatError(f"{path}: header announces {count} points, more than the limit of {MAX_POINTS} per file")
    if not compressed and offset + count * record > size:
        raise FormatError(f"{path}: header announces {count} points x {record} bytes from byte {offset}, but the "
                          f"file has {size} bytes. Hint: truncated file or a corrupt header")
    if compressed and count * record > 64 * max(size, 1):
        raise FormatError(f"{path}: LAZ header announces {count * record} bytes of points from a {size}-byte file "
                          "(ratio over 64)")


def read_las_points(path: Path) -> ScanPoints:
    import laspy

    try:
        # From memory: laspy reads header fields with stream.read(n), and a file object preallocates n bytes
        # (a corrupt 4-byte size took 1.2 GB); an in-memory stream never returns more than it holds.
        if path.stat().st_size > MAX_POINTS * 64:
            raise FormatError(f"{path}: {path.stat().st_size} bytes, more than a scan file may hold")
        raw = path.read_bytes()
        check_las_record_counts(path, raw, len(raw))
        _check_las_sizes(path, len(raw), laspy.open(io.BytesIO(raw)))
        las = laspy.read(io.BytesIO(raw))
    except FormatError:
        raise
    except FileNotFoundError as exc:
        raise DatasetIOError(f"{path}: LAS file not found") from exc
    except Exception as exc:  # laspy/lazrs raise many types for corrupt files  # noqa: BLE001
        raise FormatError(f"{path}: not a readable LAS/LAZ file: {type(exc).__name__}: {exc}") from exc
    names = set(las.point_format.dimension_names)
    time = relative_time_s(np.asarray(las.gps_time), "gps_time") if "gps_time" in names else (None, None)
    with np.errstate(over="ignore"):  # a coordinate beyond float32 becomes inf: dropped as non-finite, counted
        xyz = [np.asarray(c, np.float32) for c in (las.x, las.y, las.z)]
    return ScanPoints(*xyz, np.asarray(las.intensity, np.float32), None, *time)


def read_pcd_points(path: Path) -> ScanPoints:
    return points_from_pcd(read_pcd(path), str(path))


def read_scan(path: str | Path, fmt: str) -> ScanPoints:
    """Read one scan file of a format of the table (``scan_format_table.SCAN_FORMATS``) with its reader."""
    path = Path(path)
    if fmt not in SCAN_FORMAT_NAMES:
        raise FormatError(f"{path}: unknown scan format {fmt!r}; expected one of {', '.join(SCAN_FORMAT_NAMES)}")
    return globals()[scan_format(fmt).reader](path)


def drop_invalid_points(points: ScanPoints, min_range_m: float = 0.0) -> tuple[ScanPoints, dict[str, int]]:
    """Drop non-finite points (a coordinate or the time), exact (0,0,0) points and points closer than ``min_range_m``;
    count each."""
    x, y, z = points.x_m, points.y_m, points.z_m
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    if points.time_offset_s is not None:  # a point without a time cannot be deskewed: dropped with the non-finite
        finite &= np.isfinite(points.time_offset_s)
    zero = finite & (x == 0) & (y == 0) & (z == 0)
    keep = finite & ~zero
    counts = {"nonfinite": int((~finite).sum()), "zero": int(zero.sum()), "near": 0}
    if min_range_m > 0:
        near = keep & ((x.astype(np.float64) ** 2 + y.astype(np.float64) ** 2 + z.astype(np.float64) ** 2)
                       < min_range_m ** 2)
        counts["near"] = int(near.sum())
        keep &= ~near
    if keep.all():
        return points, counts
    return points.select(keep), counts
