"""A synthetic folder in KITTI raw's exact layout (the date folder's calib_imu_to_velo.txt; the drive folder's
velodyne_points/data/*.bin with timestamps*.txt and oxts/data/*.txt with timestamps.txt): drive init drafts a drive
file that drive check passes with nothing to change but the CHECK lines, and ingest reads the OXTS fixes, the scan
stamps and the extrinsic right; malformed OXTS files are named errors."""
from __future__ import annotations

import numpy as np
import pymap3d
import pytest
import yaml

from pipeline.errors import FormatError
from stages.common.geometry import se3_inverse
from stages.ingest.kitti_raw import read_calib_imu_to_velo, read_oxts_columns, read_stamp_lines
from stages.ingest.sensors import SENSORS

CALIB = ("calib_time: 25-May-2012 16:47:16\nR: 9.999976e-01 7.553071e-04 -2.035826e-03 -7.854027e-04 9.998898e-01 "
         "-1.482298e-02 2.024406e-03 1.482454e-02 9.998881e-01\nT: -8.086759e-01 3.195559e-01 -7.997231e-01\n")
ORIGIN = (49.0111, 8.4164, 115.0)
N = 5


def _bin_scan(rng) -> np.ndarray:
    """A laser-by-laser HDL-64E-like scan (KITTI's .bin order: each line sweeps azimuth 0 -> 360 deg)."""
    table = np.asarray(SENSORS["hdl64e"].elevations_deg) + 0.2
    rows = []
    for b in rng.permutation(64):
        az = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
        r = rng.uniform(8.0, 40.0, az.size)
        e = np.radians(table[b])
        rows.append(np.column_stack([r * np.cos(e) * np.cos(az), r * np.cos(e) * np.sin(az), r * np.sin(e),
                                     rng.uniform(0, 1, az.size)]))
    return np.concatenate(rows).astype("<f4")


def kitti_folder(root, n: int = N):
    rng = np.random.default_rng(0)
    date = root / "2011_09_26"
    drive = date / "2011_09_26_drive_0048_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "oxts" / "data").mkdir(parents=True)
    (date / "calib_imu_to_velo.txt").write_text(CALIB)
    for i in range(n):
        _bin_scan(rng).tofile(drive / "velodyne_points" / "data" / f"{i:010d}.bin")
    for name, offset in (("timestamps_start.txt", 0.0), ("timestamps.txt", 0.05), ("timestamps_end.txt", 0.1)):
        (drive / "velodyne_points" / name).write_text(
            "".join(f"2011-09-26 13:02:{25 + 0.1 * i + offset:012.9f}\n" for i in range(n)))
    for i in range(n + 2):
        lat, lon, h = pymap3d.enu2geodetic(0.9 * i, 0.0, 0.0, *ORIGIN)
        vals = [lat, lon, h, 0.01, -0.02, 0.3] + [0.0] * 2 + [9.0, 0.0, 0.0] + [0.0] * 11 + [0.02] + \
            [0.35, 0.5, 4, 10, 5, 5, 5]
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(f"{v:.12g}" for v in vals) + "\n")
    (drive / "oxts" / "timestamps.txt").write_text(
        "".join(f"2011-09-26 13:02:{24.95 + 0.1 * i:012.9f}\n" for i in range(n + 2)))
    return drive


def test_drive_init_reads_kitti_raw_as_published_and_ingest_agrees(tmp_path):
    from stages.common.geodesy import EnuOrigin
    from stages.ingest.compute import DriveIngest
    from stages.ingest.drive_check import check_drive
    from stages.ingest.drive_file import load_drive_file
    from stages.ingest.drive_init import draft_drive_file
    from stages.ingest.params import IngestParams

    drive = kitti_folder(tmp_path)
    draft = draft_drive_file(drive)
    text = "\n".join(draft.lines) + "\n"
    assert draft.todo == [], draft.todo
    doc = yaml.safe_load(text)
    assert doc["scans"] == {"folder": "velodyne_points/data", "format": "kitti_bin"} and doc["sensor"] == "hdl64e"
    assert doc["scan_times"] == {"source": "stamps_lines", "file": "velodyne_points/timestamps_start.txt"}
    T = np.asarray(doc["T_vehicle_lidar"], float)
    assert T == pytest.approx(se3_inverse(read_calib_imu_to_velo(drive.parent / "calib_imu_to_velo.txt")), abs=2e-7)
    assert T[:3, 3] == pytest.approx([0.8105, -0.3071, 0.8027], abs=1e-4)  # the lidar ahead, right of, above the IMU
    g = doc["gnss"]
    assert g["format"] == "kitti_oxts" and g["file"] == "oxts" and g["heading_convention"] == "enu_yaw_ccw_from_east"
    assert g["columns"]["std_east"] == "pos_accuracy" and g["angle_unit"] == "rad"
    assert doc["odometry"] == {"file": "oxts", "format": "kitti_oxts", "time_column": "time", "speed": "vf",
                               "yaw_rate": "wu"}
    (drive / "drive.yaml").write_text(text)
    check = check_drive(drive / "drive.yaml")
    assert check.problems == [], check.problems
    assert "frame: the GNSS/INS fixes of oxts" in check.summary
    spec = load_drive_file(drive / "drive.yaml")
    ingest = DriveIngest("k", spec, IngestParams(), EnuOrigin(*ORIGIN))
    assert [s.stamp_ns for s in ingest.scans] == [1317042145_000_000_000 + i * 100_000_000 for i in range(N)]
    poses = ingest.poses_table()
    assert poses["valid"].to_pylist() == [True] * N
    assert poses["x_m"].to_numpy() == pytest.approx(0.9 * (np.arange(N) + 0.5), abs=2e-3)  # fixes 0.05 s earlier
    assert ingest.gnss.std_enu_m[0, :2] == pytest.approx([0.35, 0.35])


def test_stamp_lines_numbers_and_date_times(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("2011-09-26 13:02:25.964389445\n1317042145.5\n1317042145600000000\n1317042145700000\nxx\n\n")
    stamps, issues = read_stamp_lines(path)
    assert stamps[:4] == [1317042145964389445, 1317042145500000000, 1317042145600000000, 1317042145700000000]
    assert stamps[4] is None and issues == [(4, "line 5: 'xx' is not a stamp (expected YYYY-MM-DD HH:MM:SS.fraction "
                                                "or a number of seconds)")]


def test_malformed_oxts_folders_are_named_errors(tmp_path):
    drive = kitti_folder(tmp_path)
    oxts = drive / "oxts"
    (oxts / "data" / "0000000003.txt").write_text("1 2 3\n")
    with pytest.raises(FormatError, match=r"0000000003\.txt: line 1 holds 3 numbers; expected 30"):
        read_oxts_columns(oxts, ["lat", "time"])
    (oxts / "data" / "0000000003.txt").unlink()
    with pytest.raises(FormatError, match=r"6 data files but 7 lines in timestamps\.txt"):
        read_oxts_columns(oxts, ["lat"])
    with pytest.raises(FormatError, match="OXTS has no column.*latitude"):
        read_oxts_columns(oxts, ["latitude"])
