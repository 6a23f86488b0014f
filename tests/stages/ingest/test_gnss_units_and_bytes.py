"""GNSS files as they arrive: a bad byte in a column ingest never uses, in one it uses, latitude/longitude in radians
declared as degrees, fixes beyond the map's area; the drive check's completeness and content fingerprint."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import DataQualityError, FormatError
from stages.common.geodesy import EnuOrigin
from stages.ingest.csv_columns import read_header
from stages.ingest.drive_file import GnssSpec
from stages.ingest.gnss_csv import check_within_area, read_gnss

SPEC = GnssSpec.model_validate({"file": "g.csv", "time": {"column": "time", "base": "unix"},
                                "columns": {"lat": "lat", "lon": "lon", "height": "alt", "heading": "yaw"},
                                "angle_unit": "rad", "heading_convention": "enu_yaw_ccw_from_east"})


def _track(n: int = 200, lat0: float = 37.4979, lon0: float = 127.0276, speed_mps: float = 10.0) -> np.ndarray:
    """(time, lat, lon) of a drive north at ``speed_mps``, 10 Hz."""
    t = 1_700_000_000.0 + 0.1 * np.arange(n)
    lat = lat0 + np.degrees(speed_mps * (t - t[0]) / 6_371_000.0)
    return np.column_stack([t, lat, np.full(n, lon0)])


def _write(tmp_path: Path, track: np.ndarray, status: list[bytes] | None = None) -> Path:
    lines = [b"time,lat,lon,alt,yaw,status"]
    for k, (t, la, lo) in enumerate(track):
        cell = status[k] if status else b"INS_GOOD"
        lines.append(f"{t:.3f},{la:.12f},{lo:.12f},57.0,0.5,".encode() + cell)
    path = tmp_path / "g.csv"
    path.write_bytes(b"\n".join(lines) + b"\n")
    return path


def test_a_bad_byte_in_a_column_ingest_does_not_use_changes_nothing(tmp_path):
    status = [b"INS_GOOD"] * 200
    status[5] = b"INS_\xff\xfeGOOD"  # 8 kB into the file: the old header reader decoded that far and failed
    fixes, issues = read_gnss(_write(tmp_path, _track(), status), SPEC)
    assert len(fixes.stamp_ns) == 200 and issues == []


def test_a_bad_byte_in_a_used_column_rejects_its_row_naming_line_and_column(tmp_path):
    path = _write(tmp_path, _track())
    lines = path.read_bytes().split(b"\n")
    lines[8] = lines[8].replace(b"37.49", b"37.\xff9", 1)  # file line 9: record 7
    path.write_bytes(b"\n".join(lines))
    fixes, issues = read_gnss(path, SPEC)
    assert len(fixes.stamp_ns) == 199 and 7 not in fixes.records
    assert [(i.record, i.reason) for i in issues] == [(7, "line 9, column 'lat': is not UTF-8 text")]


def test_a_header_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "h.csv"
    path.write_bytes(b"time,l\xffat\n1,2\n")
    with pytest.raises(FormatError, match=r"h.csv: line 1 \(the header\) is not UTF-8 text"):
        read_header(path)


def test_radians_declared_as_degrees_are_refused_with_what_was_expected(tmp_path):
    track = _track()
    track[:, 1:] = np.radians(track[:, 1:])
    with pytest.raises(FormatError, match="these are radians, but the drive file says degrees.*expected degrees"):
        read_gnss(_write(tmp_path, track), SPEC)
    rad = SPEC.model_copy(update={"latlon_unit": "rad"})
    fixes, _ = read_gnss(_write(tmp_path, track), rad)  # declared as radians: read, and in degrees
    assert np.allclose(fixes.lat_deg, _track()[:, 1])


def test_a_drive_near_0n_0e_in_degrees_is_not_taken_for_radians(tmp_path):
    fixes, _ = read_gnss(_write(tmp_path, _track(lat0=0.3, lon0=1.2)), SPEC)  # open sea off Ghana, 10 m/s
    assert len(fixes.stamp_ns) == 200


def test_fixes_beyond_the_maps_area_are_a_data_quality_error_naming_drive_and_distance(tmp_path):
    origin = EnuOrigin(37.4979, 127.0276, 57.0)
    near, _ = read_gnss(_write(tmp_path, _track()), SPEC)
    check_within_area(near, origin, 10_000.0, "drive_0", "g.csv")  # 200 m from the origin
    far, _ = read_gnss(_write(tmp_path, _track(lat0=37.9979, lon0=126.3276)), SPEC)  # +0.5 deg, -0.7 deg
    with pytest.raises(DataQualityError, match=r"drive drive_far: g.csv record \d+ lies 8\d\.\d km .* area of 10 km"):
        check_within_area(far, origin, 10_000.0, "drive_far", "g.csv")
    check_within_area(far, origin, None, "drive_far", "g.csv")  # an unbounded map
