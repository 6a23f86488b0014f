"""The real samples in ../shared/data: KITTI PCD (rings from point order), nuScenes HDL-32E, Amsterdam LAZ."""
from __future__ import annotations

import re

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
import yaml

from pipeline.declare import PartitionKey
from pipeline.testing import make_context
from stages.common.geodesy import projected_to_geodetic
from stages.ingest.compute import compute
from stages.ingest.params import IngestParams
from stages.ingest.scan_formats import read_scan
from stages.ingest.sensors import SENSORS, elevation_deg, rings_from_elevation, rings_from_elevation_voted

pytestmark = pytest.mark.realdata
IDENTITY = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def _drive(tmp_path, name, data_dir, spec):
    """A drive folder whose scans/ (and survey/) are symlinks to the read-only samples."""
    drive_dir = tmp_path / name
    drive_dir.mkdir()
    (drive_dir / "scans").symlink_to(data_dir, target_is_directory=True)
    (drive_dir / "drive.yaml").write_text(yaml.safe_dump({"name": name, **spec}))
    return drive_dir / "drive.yaml"


def _ingest(drive_file, name, origin=None, **params):
    ctx = make_context("ingest", IngestParams(**params), partition=PartitionKey(drive=name),
                       drives={name: drive_file}, settings={"enu_origin": origin})
    out = compute(ctx)
    return {k: pa.concat_tables([v] if isinstance(v, pa.Table) else list(v)) for k, v in out.items() if k != "_extra"}


def test_kitti_pcd_scans_give_64_monotone_rings_from_point_order(shared_data, tmp_path):
    spec = {"sensor": "hdl64e", "scans": {"folder": "scans", "format": "pcd"}, "scan_rate_hz": 10.0,
            "T_vehicle_lidar": IDENTITY}
    out = _ingest(_drive(tmp_path, "kitti", shared_data / "kitti_raw_0048_city", spec), "kitti")
    index = out["scan_index"].to_pylist()
    assert len(index) == 22 and all(r["status"] == "ok" for r in index)
    assert all(r["ring_source"] == "point_order" and r["rings_present"] == 64 for r in index)
    assert all(r["n_dropped_zero"] >= 1 for r in index)  # the trailing (0,0,0,0) record
    assert out["report"].filter(pc.equal(out["report"]["kind"], "ring_coverage")).num_rows == 0
    scans = out["scans"]
    for scan_id in (0, 21):
        one = scans.filter(pc.equal(scans["scan_id"], scan_id))
        elev = elevation_deg(one["x_m"].to_numpy(), one["y_m"].to_numpy(), one["z_m"].to_numpy())
        ring = one["ring"].to_numpy()
        medians = np.array([np.median(elev[ring == r]) for r in range(64)])
        assert np.all(np.diff(medians) > 0), "ring 0 lowest, elevation rising with the ring"
        assert medians[0] == pytest.approx(-24.0, abs=1.5) and medians[-1] == pytest.approx(2.5, abs=1.0)
    # no GNSS: one row per scan without a fix (the pose graph places the drive from poses_prior)
    assert out["poses_gnss"].num_rows == 22 and not any(out["poses_gnss"]["valid"].to_pylist())
    assert out["drive_info"]["origin_lat_deg"].is_null().to_pylist() == [False]


def test_nuscenes_rings_from_file_agree_with_the_elevation_table(shared_data):
    path = next((shared_data / "nuscenes_hdl32e_sweep").glob("*.pcd.bin"))
    points = read_scan(path, "nuscenes_bin")
    assert len(points) == 34688 and np.bincount(points.ring).tolist() == [1084] * 32
    table = SENSORS["hdl32e"].elevations_deg
    voted, used_vote = rings_from_elevation_voted(points.x_m, points.y_m, points.z_m, table)
    assert used_vote and np.mean(voted == points.ring) > 0.99
    per_point = rings_from_elevation(points.x_m, points.y_m, points.z_m, table)
    far = np.hypot(points.x_m, points.y_m) > 10.0
    assert np.mean(per_point[far] == points.ring[far]) > 0.85  # nearest-beam alone, honest number


def test_nuscenes_drive_stamps_from_the_file_name(shared_data, tmp_path):
    spec = {"sensor": "hdl32e", "scans": {"folder": "scans", "format": "nuscenes_bin"}, "scan_rate_hz": 20.0,
            "T_vehicle_lidar": IDENTITY, "scan_times": {"source": "filename_us"}}
    out = _ingest(_drive(tmp_path, "nusc", shared_data / "nuscenes_hdl32e_sweep", spec), "nusc")
    (row,) = out["scan_index"].to_pylist()
    assert row["stamp_ns"] == 1532402927647951000 and row["ring_source"] == "file" and row["rings_present"] == 32


def test_amsterdam_laz_survey_to_enu(shared_data, tmp_path):
    tile = "2294_9700"
    x0, y0 = 2294 * 50.0, 9700 * 50.0
    lat, lon, h = projected_to_geodetic(np.array([x0 + 25]), np.array([y0 + 25]), np.array([0.0]), "EPSG:28992")[0]
    survey_dir = tmp_path / "survey"
    survey_dir.mkdir()
    (survey_dir / "tile.laz").symlink_to(shared_data / "amsterdam_mls_laz" / f"{tile}.laz")
    spec = {"sensor": "generic", "scans": {"folder": "scans", "format": "las"}, "scan_rate_hz": 1.0,
            "T_vehicle_lidar": IDENTITY, "survey": {"file": "../survey/tile.laz", "crs": "EPSG:28992"}}
    out = _ingest(_drive(tmp_path, "ams", survey_dir, spec), "ams",
                  {"lat_deg": lat, "lon_deg": lon, "h_m": h}, survey_chunk_points=10_000)
    survey = out["survey"]
    assert survey.num_rows == 44566
    e, n = survey["east_m"].to_numpy(), survey["north_m"].to_numpy()
    # RD New is a conformal projection with scale ~0.9999 here and a grid convergence of ~1.3 deg near
    # Amsterdam: the 50 m tile stays a ~50 m square about the origin, rotated by less than 2 deg.
    assert np.all(np.abs(e) < 26.5) and np.all(np.abs(n) < 26.5)
    assert e.max() - e.min() > 30 and np.all(np.isfinite(survey["up_m"].to_numpy()))
    assert out["scan_index"].num_rows == 1 and out["scan_index"]["n_points"].to_pylist() == [44566]
    # the tile's gps_time spans many passes (hours), no sweep: its points are kept untimed, and the report says why
    assert np.all(out["scans"]["time_offset_s"].to_numpy() == 0)
    deskew = out["report"].filter(pc.equal(out["report"]["kind"], "deskew")).to_pylist()
    assert len(deskew) == 1 and deskew[0]["count"] == 44566
    assert re.match(r"gps_time of point \d+ lies \d+(\.\d+)? s from the scan start .*not deskewed", deskew[0]["reason"])
