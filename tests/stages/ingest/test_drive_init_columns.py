"""drive init reads the column names recorders write (KITTI OXTS CSVs, NovAtel INSPVAX exports, ROS NavSatFix
exports in both flattening styles, ``yaw_enu_rad``), and the drafted GNSS section reads the values right: ROS stamps
in ns and as secs + nsecs, INSPVAX height + undulation, covariances as variances, headings in their convention."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from stages.ingest.drive_file import GnssSpec
from stages.ingest.drive_init import draft_drive_file
from stages.ingest.gnss_csv import read_gnss

LAT, LON, H = 49.011, 8.416, 112.0


def _draft(folder, header: list[str], rows: list[list]) -> tuple[dict, list[str]]:
    (folder / "scans").mkdir(exist_ok=True)
    (folder / "nav.csv").write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    draft = draft_drive_file(folder)
    doc = yaml.safe_load("\n".join(line for line in draft.lines if not line.lstrip().startswith("#")))
    return doc, draft.lines


def _fixes(folder, doc):
    fixes, issues = read_gnss(folder / doc["gnss"]["file"], GnssSpec.model_validate(doc["gnss"]))
    assert issues == []
    return fixes


def test_kitti_oxts_csv_gives_gnss_and_odometry_from_one_file(tmp_path):
    header = ["time", "lat", "lon", "alt", "roll", "pitch", "yaw", "vf", "wu"]
    rows = [[1317042145.0 + 0.1 * i, LAT + 1e-6 * i, LON, H, 0.01, -0.02, 1.2, 8.5, 0.01] for i in range(20)]
    doc, lines = _draft(tmp_path, header, rows)
    g = doc["gnss"]
    assert g["columns"] == {"lat": "lat", "lon": "lon", "height": "alt", "heading": "yaw", "roll": "roll",
                            "pitch": "pitch"}
    assert g["time"] == {"column": "time", "base": "unix"} and g["angle_unit"] == "rad"
    assert g["heading_convention"] == "enu_yaw_ccw_from_east"
    assert doc["odometry"]["file"] == "nav.csv" and doc["odometry"]["speed"] == "vf"
    assert _fixes(tmp_path, doc).yaw_enu_rad == pytest.approx(np.full(20, 1.2))


def test_novatel_inspvax_export_height_plus_undulation(tmp_path):
    header = ["week", "seconds", "latitude", "longitude", "height", "undulation", "north_velocity",
              "east_velocity", "up_velocity", "roll", "pitch", "azimuth", "latitude_std", "longitude_std",
              "height_std", "azimuth_std"]
    rows = [[2200, 345600 + 0.1 * i, LAT, LON + 1e-6 * i, 95.0, 17.0, 0, 8, 0, 0.5, -1.0, 90.0, 0.02, 0.03, 0.05,
             0.1] for i in range(20)]
    doc, _ = _draft(tmp_path, header, rows)
    g = doc["gnss"]
    assert g["time"] == {"column": "seconds", "week_column": "week", "base": "gps"}
    assert g["columns"]["undulation"] == "undulation" and g["columns"]["std_north"] == "latitude_std"
    assert g["columns"]["std_east"] == "longitude_std" and g["columns"]["std_heading"] == "azimuth_std"
    assert g["heading_convention"] == "azimuth_cw_from_north" and g["angle_unit"] == "deg"
    fixes = _fixes(tmp_path, doc)
    assert fixes.h_m == pytest.approx(np.full(20, 112.0))  # above mean sea level + undulation = ellipsoidal
    assert fixes.yaw_enu_rad == pytest.approx(np.zeros(20), abs=1e-12)  # azimuth 90 (east) = ENU yaw 0


def test_ros_navsatfix_rostopic_export(tmp_path):
    header = ["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id", "field.status.status",
              "field.latitude", "field.longitude", "field.altitude"] + \
        [f"field.position_covariance{i}" for i in range(9)] + ["field.position_covariance_type"]
    rows = [[1690000000000000000 + i * 100_000_000 + 7, i, 1690000000000000000 + i * 100_000_000, "gps", 2,
             LAT, LON + 1e-6 * i, H, 0.04, 0, 0, 0, 0.09, 0, 0, 0, 0.25, 2] for i in range(20)]
    doc, lines = _draft(tmp_path, header, rows)
    g = doc["gnss"]
    assert g["time"] == {"column": "field.header.stamp", "unit": "ns", "base": "unix"}, g["time"]
    assert g["columns"]["lat"] == "field.latitude" and g["columns"]["height"] == "field.altitude"
    assert g["columns"]["std_east"] == "field.position_covariance0" and g["std_is_variance"] is True
    assert any("heading: HEADING  # TODO: no heading column recognised (NavSatFix has none" in ln for ln in lines)
    g["columns"]["heading"] = "field.altitude"  # any column, to read the rest
    g["heading_convention"] = "enu_yaw_ccw_from_east"
    fixes = _fixes(tmp_path, doc)
    assert np.diff(fixes.stamp_ns) == pytest.approx(np.full(19, 100_000_000), abs=300)  # ns, float64 at 1.7e18
    assert fixes.std_enu_m[0] == pytest.approx([0.2, 0.3, 0.5])  # sqrt of the covariance's diagonal


def test_ros_bag_csv_secs_nsecs_and_yaw_enu_rad(tmp_path):
    header = ["Time", "header.seq", "header.stamp.secs", "header.stamp.nsecs", "header.frame_id", "latitude",
              "longitude", "altitude", "yaw_enu_rad"]
    rows = [[1690000000.1 * i, i, 1690000000 + i // 10, (i % 10) * 100_000_000, "gps", LAT, LON + 1e-6 * i, H,
             0.7] for i in range(20)]
    doc, lines = _draft(tmp_path, header, rows)
    g = doc["gnss"]
    assert g["time"]["column"] == "header.stamp.secs" and g["time"]["nanosec_column"] == "header.stamp.nsecs"
    assert g["columns"]["heading"] == "yaw_enu_rad" and g["angle_unit"] == "rad"
    assert g["heading_convention"] == "enu_yaw_ccw_from_east"
    assert any("heading_convention: enu_yaw_ccw_from_east  # the column name 'yaw_enu_rad' says ENU yaw" in ln
               for ln in lines), lines
    fixes = _fixes(tmp_path, doc)
    assert np.diff(fixes.stamp_ns) == pytest.approx(np.full(19, 100_000_000), abs=1000)
    assert fixes.yaw_enu_rad == pytest.approx(np.full(20, 0.7))
