"""A sensor's own beam table, read from the calibration file its maker's tools write:

- Ouster metadata JSON (``beam_altitude_angles``, at the top level in the legacy format, under ``beam_intrinsics``
  since firmware 2.x; the model in ``prod_line``, top level or under ``sensor_info``). Legacy 16/32-beam files list
  64 slots with the unused ones as (altitude 0, azimuth 0): those are dropped.
- Velodyne VeloView / driver ``db.xml`` (``points_`` items ``px`` with ``id_`` and ``vertCorrection_`` in degrees;
  ``enabled_`` marks the lasers the unit has).
- Hesai angle-correction CSV (a header line naming ``Elevation``, then ``channel, elevation deg, azimuth deg``).

Each returns the table ascending (ring 0 = lowest) and the ``SENSORS`` model it belongs to: the Ouster ``prod_line``
when it names one, else the model with as many beams whose table is nearest (RMS, degrees). Every malformed file is
a ``FormatError`` naming the file and what was expected.
"""
from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline.errors import DatasetIOError, FormatError

MAX_CALIBRATION_BYTES = 4 << 20  # metadata JSONs are 10-60 kB; a db.xml ~60 kB


@dataclass(frozen=True)
class BeamCalibration:
    elevations_deg: tuple[float, ...]  # ascending: index = ring
    kind: str  # ouster_metadata | velodyne_xml | hesai_csv
    model: str | None  # the SENSORS name it belongs to, or None
    why: str  # how the model was told (prod_line, or nearest table and its RMS)


def _text(path: Path) -> str:
    try:
        size = path.stat().st_size
        if size > MAX_CALIBRATION_BYTES:
            raise FormatError(f"{path}: {size} bytes, more than the {MAX_CALIBRATION_BYTES}-byte limit of a "
                              "calibration file")
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not UTF-8 text (byte {exc.start}); expected an Ouster metadata JSON, a Velodyne "
                          "db.xml or a Hesai angle-correction CSV") from None
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read calibration file: {exc.strerror or exc}") from exc


def _checked(path: Path, values: list, what: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(f"{path}: {what} holds a value that is not a number; expected elevation angles in "
                          "degrees") from None
    if arr.ndim != 1 or len(arr) < 2:
        raise FormatError(f"{path}: {what}: expected a list of at least 2 elevation angles, got {len(arr)}")
    bad = ~np.isfinite(arr) | (np.abs(arr) >= 90.0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(f"{path}: {what}[{i}] = {float(arr[i])!r}; expected an elevation in degrees within +-90")
    if len(np.unique(arr)) != len(arr):
        raise FormatError(f"{path}: {what}: two beams share an elevation; expected one elevation per beam")
    return tuple(float(v) for v in np.sort(arr))


def _ouster(path: Path) -> tuple[tuple[float, ...], str | None]:
    try:
        doc = json.loads(_text(path))
    except json.JSONDecodeError as exc:
        raise FormatError(f"{path}: line {exc.lineno}: not JSON ({exc.msg}); expected an Ouster metadata "
                          "file") from None
    if not isinstance(doc, dict):
        raise FormatError(f"{path}: expected a JSON object (Ouster metadata), got {type(doc).__name__}")
    beams = doc.get("beam_intrinsics") if isinstance(doc.get("beam_intrinsics"), dict) else doc
    altitude, azimuth = beams.get("beam_altitude_angles"), beams.get("beam_azimuth_angles")
    if not isinstance(altitude, list):
        raise FormatError(f"{path}: no beam_altitude_angles list (top level or under beam_intrinsics); expected "
                          "an Ouster metadata JSON")
    if isinstance(azimuth, list) and len(azimuth) == len(altitude):
        unused = [a == 0 and z == 0 for a, z in zip(altitude, azimuth)]
        if 0 < sum(unused) <= len(altitude) // 2 and not all(unused):
            altitude = [a for a, u in zip(altitude, unused) if not u]
    info = doc.get("sensor_info") if isinstance(doc.get("sensor_info"), dict) else doc
    prod_line = info.get("prod_line")
    return _checked(path, altitude, "beam_altitude_angles"), (str(prod_line) if prod_line else None)


def _velodyne(path: Path) -> tuple[float, ...]:
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(_text(path))
    except ET.ParseError as exc:
        raise FormatError(f"{path}: line {exc.position[0]}: not XML ({exc}); expected a Velodyne db.xml") from None
    enabled = [e.text.strip() != "0" for e in root.findall(".//enabled_/item") if e.text is not None]
    by_id = {}
    for px in root.iter("px"):
        pid, vert = px.findtext("id_"), px.findtext("vertCorrection_")
        if pid is None or vert is None:
            continue
        try:
            by_id[int(pid)] = float(vert)
        except ValueError:
            raise FormatError(f"{path}: laser id_ {pid!r}: vertCorrection_ {vert!r} is not a number") from None
    if not by_id:
        raise FormatError(f"{path}: no points_/px items with id_ and vertCorrection_; expected a Velodyne db.xml")
    ids = [i for i in sorted(by_id) if not enabled or (i < len(enabled) and enabled[i])]
    return _checked(path, [by_id[i] for i in ids], "vertCorrection_")


def _hesai(path: Path) -> tuple[float, ...]:
    rows = list(csv.reader(io.StringIO(_text(path))))
    if not rows or not any("elevation" in c.strip().lower() for c in rows[0]):
        raise FormatError(f"{path}: line 1 {rows[0] if rows else ''!r}: expected a header naming Elevation "
                          "(Hesai angle-correction CSV: Channel,Elevation,Azimuth)")
    col = next(i for i, c in enumerate(rows[0]) if "elevation" in c.strip().lower())
    values = []
    for line, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        try:
            values.append(float(row[col]))
        except (IndexError, ValueError):
            raise FormatError(f"{path}: line {line}: {','.join(row)[:60]!r}: no number in the Elevation column "
                              f"(column {col + 1})") from None
    return _checked(path, values, "Elevation")


def nearest_model(elevations_deg: tuple[float, ...]) -> tuple[str | None, float]:
    """The SENSORS model with as many beams whose table is nearest (RMS deg), and that RMS; (None, inf) if none."""
    from stages.ingest.sensors import SENSORS

    table = np.asarray(elevations_deg, float)
    best: tuple[str | None, float] = (None, float("inf"))
    for name, model in SENSORS.items():
        if model.n_rings == len(table):
            rms = float(np.sqrt(np.mean((np.asarray(model.elevations_deg) - table) ** 2)))
            if rms < best[1]:
                best = (name, rms)
    return best


def read_beam_calibration(path: str | Path) -> BeamCalibration:
    """The beam table of a calibration file (kind from its suffix: .json Ouster, .xml Velodyne, .csv Hesai)."""
    from stages.ingest.sensors import SENSORS

    path = Path(path)
    suffix = path.suffix.lower()
    prod_line = None
    if suffix == ".json":
        table, prod_line = _ouster(path)
        kind = "ouster_metadata"
    elif suffix == ".xml":
        table, kind = _velodyne(path), "velodyne_xml"
    elif suffix == ".csv":
        table, kind = _hesai(path), "hesai_csv"
    else:
        raise FormatError(f"{path}: unknown calibration file type {suffix!r}; expected .json (Ouster metadata), .xml "
                          "(Velodyne db.xml) or .csv (Hesai angle correction)")
    by_label = [m.name for m in SENSORS.values() if prod_line and m.label.upper() == prod_line.strip().upper()]
    if by_label and SENSORS[by_label[0]].n_rings == len(table):
        return BeamCalibration(table, kind, by_label[0], f"prod_line {prod_line}")
    name, rms = nearest_model(table)
    why = (f"prod_line {prod_line}, " if prod_line else "") + (
        f"{len(table)} beams, nearest table {name} (RMS {rms:.2f} deg)" if name else f"{len(table)} beams, no model "
        "with as many")
    return BeamCalibration(table, kind, name, why)


@lru_cache(maxsize=16)
def _cached(path: str, mtime_ns: int, size: int) -> BeamCalibration:
    return read_beam_calibration(path)


def calibration_table(path: Path) -> tuple[float, ...]:
    """The ascending table of a calibration file, read once per file version (ingest asks per scan)."""
    st = Path(path).stat()
    return _cached(str(path), st.st_mtime_ns, st.st_size).elevations_deg
