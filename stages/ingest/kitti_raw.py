"""The KITTI raw layout as KITTI publishes it, and files of one stamp per line.

- ``oxts/`` (``format: kitti_oxts``): ``data/NNNNNNNNNN.txt`` holds one line of the 30 OXTS values (KITTI devkit
  ``dataformat.txt``: lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu pos_accuracy
  vel_accuracy navstat numsats posmode velmode orimode), ``timestamps.txt`` one date-time per data file, in file
  order. Read as named columns (those 30 and ``time``, unix seconds) like a CSV's.
- Stamp files (``scan_times.source: stamps_lines``): one stamp per line, line k for scan k. A line is a date-time
  ``YYYY-MM-DD HH:MM:SS[.fraction]`` (KITTI ``timestamps.txt``: read as UTC, unix base) or a number: seconds, or
  microseconds above 1e14, or nanoseconds above 1e17 (ROS stamps written as integers; 1e14 s would be 3 million
  years).
- ``calib_imu_to_velo.txt`` (``R: 9 numbers``, ``T: 3 numbers``; ``X_velo = R X_imu + T``): ``T_vehicle_lidar`` is
  its inverse when the vehicle frame is the OXTS unit's (x forward, y left, z up), the frame OXTS reports poses of.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError

OXTS_COLUMNS = ("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az", "af",
                "al", "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy", "navstat", "numsats",
                "posmode", "velmode", "orimode")
MAX_STAMP_FILE_BYTES = 64 << 20
_DATETIME = re.compile(r"^\s*(\d{4}-\d{2}-\d{2})[ T](\d{2}:\d{2}:\d{2})(\.\d{1,9})?\s*$")


def is_oxts_folder(path: Path) -> bool:
    path = Path(path)
    return (path / "timestamps.txt").is_file() and (path / "data").is_dir()


def oxts_header(folder: Path) -> list[str]:
    """The column names of an OXTS folder, as a CSV header would list them."""
    return ["time", *OXTS_COLUMNS]


def parse_stamp(text: str) -> int:
    """One stamp line -> int64 ns (see the module docstring); ValueError naming what was expected."""
    m = _DATETIME.match(text)
    if m:
        frac = (m.group(3) or ".")[1:].ljust(9, "0")
        whole = np.datetime64(f"{m.group(1)}T{m.group(2)}", "s").astype(np.int64)
        return int(whole) * 1_000_000_000 + int(frac or 0)
    value = float(text)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"{text.strip()[:40]!r} is not a time")
    if value > 1e17:
        return int(text.strip()) if text.strip().isdigit() else int(round(value))
    if value > 1e14:
        return int(round(value * 1e3))
    return int(round(value * 1e9))


def read_stamp_lines(path: Path) -> tuple[list[int | None], list[tuple[int, str]]]:
    """A file of one stamp per line -> (stamp ns per line, None where unreadable; (record, reason) per bad line).
    ``record`` is the 0-based line index (file line = record + 1)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_STAMP_FILE_BYTES:
            raise FormatError(f"{path}: more than {MAX_STAMP_FILE_BYTES} bytes; expected one stamp per line")
        lines = path.read_bytes().decode("utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not UTF-8 text (byte {exc.start}); expected one stamp per line") from None
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read stamps: {exc.strerror or exc}") from exc
    while lines and not lines[-1].strip():
        lines.pop()
    stamps: list[int | None] = []
    issues: list[tuple[int, str]] = []
    for k, line in enumerate(lines):
        try:
            stamps.append(parse_stamp(line))
        except ValueError:
            stamps.append(None)
            issues.append((k, f"line {k + 1}: {line.strip()[:40]!r} is not a stamp (expected YYYY-MM-DD "
                              "HH:MM:SS.fraction or a number of seconds)"))
    return stamps, issues


def read_oxts_columns(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Named columns of an OXTS folder as float64, one row per data file (sorted by name); ``time`` in unix seconds
    from ``timestamps.txt`` (row k = line k). A data file without 30 numbers, a time line that is no date-time, or
    a column that is no OXTS field is a FormatError naming the file and line."""
    folder = Path(folder)
    unknown = [n for n in names if n != "time" and n not in OXTS_COLUMNS]
    if unknown:
        raise FormatError(f"{folder}: OXTS has no column(s) {', '.join(unknown)}; columns: time, "
                          f"{', '.join(OXTS_COLUMNS)}. Hint: fix the column mapping in drive.yaml")
    if not is_oxts_folder(folder):
        raise FormatError(f"{folder}: not a KITTI OXTS folder; expected data/*.txt and timestamps.txt")
    files = sorted(p for p in (folder / "data").iterdir() if p.suffix == ".txt")
    stamps, issues = read_stamp_lines(folder / "timestamps.txt")
    if issues:
        raise FormatError(f"{folder / 'timestamps.txt'}: {issues[0][1]}")
    if len(stamps) != len(files):
        raise FormatError(f"{folder}: {len(files)} data files but {len(stamps)} lines in timestamps.txt; expected "
                          "one time per data file")
    rows = np.full((len(files), len(OXTS_COLUMNS)), np.nan)
    for i, f in enumerate(files):
        try:
            text = f.read_text(encoding="utf-8").split("\n")[0]
            values = [float(v) for v in text.split()]
        except (UnicodeDecodeError, ValueError):
            raise FormatError(f"{f}: line 1 is not {len(OXTS_COLUMNS)} numbers (KITTI OXTS data line)") from None
        except OSError as exc:
            raise DatasetIOError(f"{f}: cannot read: {exc.strerror or exc}") from exc
        if len(values) != len(OXTS_COLUMNS):
            raise FormatError(f"{f}: line 1 holds {len(values)} numbers; expected {len(OXTS_COLUMNS)} (KITTI OXTS: "
                              f"{' '.join(OXTS_COLUMNS[:6])} ...)")
        rows[i] = values
    out = {n: rows[:, OXTS_COLUMNS.index(n)] for n in names if n != "time"}
    if "time" in names:
        out["time"] = np.array(stamps, np.float64) * 1e-9
    return out


def read_calib_imu_to_velo(path: Path) -> np.ndarray:
    """``calib_imu_to_velo.txt`` -> T_velo_imu (4x4; maps IMU points into the velodyne frame)."""
    path = Path(path)
    values = {}
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read KITTI calibration: {exc}") from exc
    for n, line in enumerate(text.splitlines(), start=1):
        key, _, rest = line.partition(":")
        if key.strip() in ("R", "T"):
            try:
                values[key.strip()] = np.array([float(v) for v in rest.split()])
            except ValueError:
                raise FormatError(f"{path}: line {n}: {key.strip()} is not a list of numbers") from None
    R, t = values.get("R"), values.get("T")
    if R is None or t is None or R.size != 9 or t.size != 3:
        raise FormatError(f"{path}: expected 'R: 9 numbers' and 'T: 3 numbers' (KITTI calib_imu_to_velo.txt)")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), t
    return T


def vehicle_from_imu_calibration(path: Path) -> np.ndarray:
    """T_vehicle_lidar with the OXTS unit as the vehicle frame: the inverse of calib_imu_to_velo.txt's T_velo_imu."""
    from stages.common.geometry import se3_inverse

    return se3_inverse(read_calib_imu_to_velo(path))
