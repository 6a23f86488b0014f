"""A drive's prior trajectory and start pose: the poses files round trip through their one decoder, malformed lines
are named errors naming file and line, ingest places the prior in the map's frame (ENU by geodesy; a local prior
aligned at the start heading, its std grown with the distance from the start) and ``poses_prior`` round trips
through its schema."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
import yaml
from scipy.spatial.transform import Rotation

from fixtures.ingest import write_synthetic_drive
from pipeline.errors import FormatError
from schemas import SCHEMAS
from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.geometry import write_kitti, write_tum
from stages.common.records import PriorPoses, read_pose_file


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.5, (n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(0, 100, (n, 3))
    return T


def test_tum_and_kitti_files_round_trip(tmp_path):
    T = _poses(7)
    write_tum(tmp_path / "p.txt", 1e9 + np.arange(7) * 0.5, T, header="a comment")
    tum = read_pose_file(tmp_path / "p.txt", "tum", increasing=True)
    assert tum.T == pytest.approx(T, abs=1e-8) and tum.stamp_s == pytest.approx(1e9 + np.arange(7) * 0.5)
    assert tum.line.tolist() == list(range(2, 9))  # line 1 is the comment
    write_kitti(tmp_path / "k.txt", T)
    kitti = read_pose_file(tmp_path / "k.txt", "kitti")
    assert kitti.stamp_s is None and kitti.T == pytest.approx(T, abs=1e-6)  # %.9e: 10 digits


@pytest.mark.parametrize("fmt, text, match", [
    ("tum", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", r"p\.txt: line 2: 7 values; expected 8"),
    ("tum", "# c\n0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n", r"line 3: .* not a number"),
    ("tum", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0\n", r"line 2: zero quaternion"),
    ("tum", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r"line 3: time 1.0 does not increase"),
    ("tum", "0 0 0 nan 0 0 0 1\n", r"line 1: a value is not finite"),
    ("kitti", "1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", r"line 2: the 3x3 part is not a rotation"),
    ("kitti", "\n\n", r"no pose line"),
])
def test_malformed_poses_files_name_file_and_line(tmp_path, fmt, text, match):
    (tmp_path / "p.txt").write_text(text)
    with pytest.raises(FormatError, match=match):
        read_pose_file(tmp_path / "p.txt", fmt, increasing=True)


def _gnss_free(tmp_path, prior: dict, start: dict | None = None):
    """The synthetic drive (6 scans, truth known) without its GNSS section, with a prior file of its truth."""
    drive = write_synthetic_drive(tmp_path, n_scans=6)
    doc = yaml.safe_load(drive.drive_file.read_text())
    del doc["gnss"]
    doc["scan_times"] = {"source": "stamps_csv"}
    doc["prior"] = prior
    if start is not None:
        doc["start"] = start
    drive.drive_file.write_text(yaml.safe_dump(doc))
    return drive


def _truth_at_scans(drive):
    from stages.ingest.pose_interpolation import interpolate_poses

    attitude = Rotation.from_euler("z", drive.yaw_enu_rad[:, None])
    q = interpolate_poses(drive.gnss_stamps_ns, drive.vehicle_xyz_enu_m, attitude,
                          np.zeros((len(drive.yaw_enu_rad), 4)), drive.scan_stamps_ns, 1.0)
    T = np.tile(np.eye(4), (len(q.position_enu_m), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = Rotation.from_quat(q.quat_xyzw).as_matrix(), q.position_enu_m
    return T


def _ingest(drive, origin, **params):
    from stages.ingest.compute import DriveIngest
    from stages.ingest.drive_file import load_drive_file
    from stages.ingest.params import IngestParams

    return DriveIngest("drive_0", load_drive_file(drive.drive_file), IngestParams(**params), origin)


def test_an_enu_prior_about_another_origin_lands_on_the_truth_and_is_the_drives_absolute_input(tmp_path):
    drive = write_synthetic_drive(tmp_path / "tmp", n_scans=6)
    truth = _truth_at_scans(drive)
    other = EnuOrigin(37.5700, 126.9800, 60.0)  # the prior's frame: ENU about a point 400 m away
    from stages.common.trajectory_frame import move_poses

    T_other = move_poses(truth, drive.origin, other)
    (tmp_path / "d").mkdir()
    write_tum(tmp_path / "d" / "prior.txt", drive.scan_stamps_ns * 1e-9, T_other)
    d = _gnss_free(tmp_path / "d", {"file": "../prior.txt", "format": "tum", "frame": "enu", "time": "stamps",
                                    "origin": {"lat_deg": other.lat_deg, "lon_deg": other.lon_deg,
                                               "h_m": other.h_m}, "std_m": [0.1, 0.1, 0.2]})
    # by default poses_gnss holds the scans without a fix (the pose graph reads poses_prior)
    default = _ingest(d, drive.origin).poses_table()
    assert default.num_rows == 6 and not any(default["valid"].to_pylist())
    ingest = _ingest(d, drive.origin, prior_as_gnss=True)
    prior = ingest.prior()
    assert prior.valid.all() and set(prior.frame) == {"map_enu"}
    # 1e-5 m: the TUM file's float64 seconds at GPS epoch magnitude (0.2 us) times 8 m/s
    assert prior.T[:, :3, 3] == pytest.approx(truth[:, :3, 3], abs=1e-5)
    poses = ingest.poses_table()
    assert poses["x_m"].to_numpy() == pytest.approx(truth[:, 0, 3], abs=1e-5)
    assert poses["std_up_m"].to_pylist() == pytest.approx([0.2] * 6)
    assert any(r["kind"] == "prior" and "poses_gnss holds the prior" in r["reason"] for r in ingest.report.rows)
    table = ingest.prior_table()  # through the schema and back
    back = PriorPoses.from_table(table, "drive_0")
    assert back.T == pytest.approx(prior.T) and list(back.source) == ["prior_file"] * 6
    assert table.schema.equals(SCHEMAS["poses_prior"], check_metadata=False)


def test_a_local_prior_is_aligned_at_the_start_heading_with_std_growing_from_the_start(tmp_path):
    drive = write_synthetic_drive(tmp_path / "tmp", n_scans=6)
    truth = _truth_at_scans(drive)
    T_local = np.eye(4)
    T_local[:3, :3] = Rotation.from_euler("z", 1.1).as_matrix()
    T_local[:3, 3] = (30.0, -4.0, 2.0)
    (tmp_path / "d").mkdir()
    write_kitti(tmp_path / "d" / "prior.txt", T_local @ truth)
    lat, lon, h = enu_to_geodetic(truth[0, :3, 3], drive.origin)[0]
    heading = 90.0 - np.degrees(np.arctan2(truth[0, 1, 0], truth[0, 0, 0]))  # azimuth: clockwise from north
    d = _gnss_free(tmp_path / "d", {"file": "../prior.txt", "format": "kitti", "frame": "local",
                                    "time": "scan_order", "std_m": [0.05, 0.05, 0.05]},
                   {"heading_deg": float(heading), "heading_convention": "azimuth_cw_from_north",
                    "std_heading_deg": 1.0, "position": {"lat_deg": float(lat), "lon_deg": float(lon),
                                                         "h_m": float(h)}, "std_m": 0.2})
    ingest = _ingest(d, drive.origin, prior_as_gnss=True)
    rows = ingest.prior()
    assert list(rows.source) == ["prior_file"] * 6 + ["start"] and list(rows.frame) == ["local"] * 6 + ["map_enu"]
    poses = ingest.poses_table()
    assert np.column_stack([poses[c].to_numpy() for c in ("x_m", "y_m", "z_m")]) == \
        pytest.approx(truth[:, :3, 3], abs=1e-5)  # the KITTI file's 10 digits and the start's geodetic round trip
    dist = np.hypot(*(truth[:, :2, 3] - truth[0, :2, 3]).T)
    expected = np.sqrt(0.05 ** 2 + 0.2 ** 2 + (dist * np.radians(1.0)) ** 2)
    assert poses["std_east_m"].to_numpy() == pytest.approx(expected, rel=1e-4)


def test_a_prior_that_gives_no_scan_a_pose_is_a_drive_check_problem(tmp_path):
    from stages.ingest.drive_check import check_drive

    (tmp_path / "d").mkdir()
    write_tum(tmp_path / "d" / "prior.txt", np.array([1.0, 2.0]), np.tile(np.eye(4), (2, 1, 1)))
    d = _gnss_free(tmp_path / "d", {"file": "../prior.txt", "format": "tum", "frame": "enu", "time": "stamps",
                                    "origin": {"lat_deg": 37.0, "lon_deg": 127.0, "h_m": 0.0}})
    check = check_drive(d.drive_file)
    assert any("prior: ../prior.txt gives no scan a pose" in p for p in check.problems), check.problems
    assert any("a pose for 0 of 6 scans" in s for s in check.summary)


def test_poses_prior_schema_round_trip():
    rows = PriorPoses("d", np.arange(3), np.arange(3) * 10, _poses(3), np.full((3, 6), 0.1),
                      np.array(["local"] * 3, dtype=object), np.array(["prior_file"] * 3, dtype=object),
                      np.array([True, False, True]))
    table = pa.table(rows.to_columns(), schema=SCHEMAS["poses_prior"])
    back = PriorPoses.from_table(table, "d")
    assert back.T == pytest.approx(rows.T) and back.valid.tolist() == [True, False, True]
