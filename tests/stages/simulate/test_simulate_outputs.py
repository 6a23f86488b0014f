"""Files written by the simulator: determinism, formats, survey LAS with its CRS, truth consistency."""
from __future__ import annotations

import csv
import hashlib
import json

import numpy as np
import pytest
import yaml

from stages.simulate.writers import PCD_DTYPE


def read_pcd(path):
    raw = path.read_bytes()
    head, _, body = raw.partition(b"DATA binary\n")
    header = dict(line.split(" ", 1) for line in head.decode().splitlines() if not line.startswith("#"))
    assert header["FIELDS"] == "x y z intensity ring time"
    pts = np.frombuffer(body, PCD_DTYPE)
    assert len(pts) == int(header["POINTS"])
    return pts


def digests(root):
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_preset_and_seed_give_identical_files(tmp_path, tiny_sim):
    from stages.simulate.core import simulate

    simulate("tiny", 0, tmp_path / "again", n_drives=2, scan_limit=12)
    first, second = digests(tiny_sim[0]), digests(tmp_path / "again")
    assert first.keys() == second.keys()
    assert [k for k in first if first[k] != second[k]] == []
    assert len(first) > 30


def test_other_seed_gives_other_city(tmp_path, tiny_sim):
    from stages.simulate.core import simulate

    simulate("tiny", 1, tmp_path / "s1", n_drives=1, scan_limit=1)
    assert (tmp_path / "s1/truth/city.json").read_bytes() != (tiny_sim[0] / "truth/city.json").read_bytes()


def test_drive_yaml_and_streams(tiny_sim):
    out, summary = tiny_sim
    doc = yaml.safe_load((out / "drive_1/drive.yaml").read_text())
    assert doc["sensor"] == "hdl32e" and doc["scans"] == {"folder": "scans", "format": "pcd"}
    assert np.allclose(np.array(doc["T_vehicle_lidar"])[:3, 3], [0, 0, 1.9])
    assert doc["survey"]["file"] == "../survey/survey.las" and doc["survey"]["crs"] == "EPSG:32652"
    assert (out / "drive_1" / doc["survey"]["file"]).resolve().is_file()
    stamps = np.loadtxt(out / "drive_1/scans/stamps.csv", delimiter=",", skiprows=1)
    assert len(stamps) == summary.n_scans["drive_1"] == 12
    assert np.all(stamps[:, 1] == 1890) and np.allclose(np.diff(stamps[:, 2]), 0.1)
    gnss = list(csv.DictReader(open(out / "drive_1/gnss_inspva.csv")))
    assert list(gnss[0]) == ["gps_week", "gps_seconds", "latitude_deg", "longitude_deg", "height_m", "roll_deg",
                             "pitch_deg", "azimuth_deg", "std_lat_m", "std_lon_m", "std_height_m",
                             "std_azimuth_deg", "status"]
    t = np.array([float(r["gps_seconds"]) for r in gnss])
    assert np.median(np.diff(t)) == pytest.approx(0.05) and t[0] <= stamps[0, 2]
    odo = np.loadtxt(out / "drive_1/wheel_gyro.csv", delimiter=",", skiprows=1)
    assert np.all(odo[:, 0] == 1890)
    assert np.median(np.diff(odo[:, 1])) == pytest.approx(0.01) and odo[:, 2].max() <= 40 / 3.6 * 1.05
    pts = read_pcd(out / "drive_1/scans/000005.pcd")
    assert 15_000 < len(pts) < 72_000
    assert pts["time"].min() >= 0 and pts["time"].max() < 0.1 and pts["ring"].max() == 31


def test_truth_poses_match_gnss_within_the_error_model(tiny_sim):
    from stages.common.geodesy import EnuOrigin, geodetic_to_enu
    from stages.common.records import Trajectory

    out, _ = tiny_sim
    truth = Trajectory.from_tum(out / "truth/drive_0_poses_tum.txt")
    stamps, T = truth.stamp_s, truth.T
    sim = json.loads((out / "simulation.json").read_text())
    g = np.loadtxt(out / "drive_0/gnss_inspva.csv", delimiter=",", skiprows=1, usecols=range(12))
    enu = geodetic_to_enu(g[:, 2], g[:, 3], g[:, 4], EnuOrigin.from_dict(sim["enu_origin"]))
    t_gnss = g[:, 0] * 604800.0 + g[:, 1]  # the TUM truth is in full GPS seconds, the drive's time base
    e = np.interp(stamps, t_gnss, enu[:, 0]) - T[:, 0, 3]
    n = np.interp(stamps, t_gnss, enu[:, 1]) - T[:, 1, 3]
    assert 0.0 < np.hypot(e, n).max() < 3.0
    yaw_truth = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    yaw_gnss = np.radians(90.0 - np.interp(stamps, t_gnss, g[:, 7]))
    assert np.degrees(np.abs(np.angle(np.exp(1j * (yaw_gnss - yaw_truth))))).max() < 2.0


def test_survey_las_has_utm_crs_and_density(tiny_sim):
    import laspy

    las = laspy.read(tiny_sim[0] / "survey/survey.las")
    assert str(las.header.version) == "1.4"
    assert las.header.parse_crs().to_epsg() == 32652
    x, y = np.asarray(las.x), np.asarray(las.y)
    assert 300_000 < x.mean() < 400_000 and 4_100_000 < y.mean() < 4_200_000  # Seoul in UTM 52N
    counts = np.unique(np.floor(x).astype(np.int64) * 10_000_000 + np.floor(y).astype(np.int64),
                       return_counts=True)[1]
    assert np.median(counts) >= 100  # points per square metre


def test_corners_match_building_footprints(tiny_sim):
    out, _ = tiny_sim
    city = json.loads((out / "truth/city.json").read_text())
    rows = list(csv.DictReader(open(out / "truth/corners.csv")))
    verts = np.concatenate([np.array(b["footprint_en"]) for b in city["buildings"]])
    assert len(rows) == len(verts)
    got = np.array([[float(r["east_m"]), float(r["north_m"])] for r in rows])
    assert np.abs(got - verts).max() < 1e-3
    k = 0
    for b in city["buildings"]:
        fp = np.array(b["footprint_en"])
        n = len(fp)
        angles = [float(rows[k + i]["interior_angle_deg"]) for i in range(n)]
        assert sum(angles) == pytest.approx((n - 2) * 180.0, abs=0.05)  # a simple polygon
        for i in range(n):  # theta2 points along wall i to the next vertex
            d = fp[(i + 1) % n] - fp[i]
            diff = np.degrees(np.arctan2(d[1], d[0])) - float(rows[k + i]["theta2_deg"])
            assert abs((diff + 180.0) % 360.0 - 180.0) < 0.01
            glass = b["glass_walls"][i] + b["glass_walls"][i - 1]
            assert int(rows[k + i]["glass_walls"]) == glass
        k += n
    vis = np.array([int(r["scans_visible_0"]) for r in rows])
    assert vis.max() > 0 and vis.max() <= 12
