"""compute() on in-memory tables: chunk overlap, vehicle-frame edges against truth, malformed inputs."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation

from pipeline.declare import PartitionKey
from pipeline.errors import FormatError
from pipeline.testing import make_context
from schemas.registry import schema_of
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.odometry.params import OdometryParams
from tests.stages.odometry.conftest import raycast_scan

T_VEHICLE_LIDAR = se3_from_xyz_rpy(0.8, 0.0, 1.9, 0.0, 0.01, 0.02)


def _truth(n: int) -> np.ndarray:
    """Vehicle poses in ENU: 1 m steps with a gentle turn."""
    T = [np.eye(4)]
    for _ in range(n - 1):
        T.append(T[-1] @ se3_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, 0.01))
    return np.array(T)


def _tables(scene, T_map_vehicle, chunk_of, drive="d0", seed=0):
    rng = np.random.default_rng(seed)
    parts = []
    for sid, T in enumerate(T_map_vehicle):
        pts = raycast_scan(scene, T @ T_VEHICLE_LIDAR, rng, noise_m=0.01).astype(np.float32)
        n = len(pts)
        parts.append(pa.table({
            "drive": [drive] * n, "chunk": pa.array([chunk_of(sid)] * n, pa.int32()),
            "scan_id": pa.array([sid] * n, pa.int64()), "stamp_ns": pa.array([sid * 100_000_000] * n, pa.int64()),
            "x_m": pts[:, 0], "y_m": pts[:, 1], "z_m": pts[:, 2],
            "intensity": np.zeros(n, np.float32), "ring": np.zeros(n, np.int16),
            "time_offset_s": np.zeros(n, np.float32)}, schema=schema_of("scans_raw")))
    scans = pa.concat_tables(parts)
    n = len(T_map_vehicle)
    noisy = T_map_vehicle.copy()
    noisy[:, :2, 3] += rng.normal(0, 0.05, (n, 2))  # 10 Hz GNSS/INS increments: good to ~0.1 m
    q = Rotation.from_matrix(noisy[:, :3, :3]).as_quat()
    gnss = pa.table({
        "drive": [drive] * n, "scan_id": pa.array(range(n), pa.int64()),
        "stamp_ns": pa.array([i * 100_000_000 for i in range(n)], pa.int64()),
        "x_m": noisy[:, 0, 3], "y_m": noisy[:, 1, 3], "z_m": noisy[:, 2, 3],
        "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
        "std_east_m": np.full(n, 0.3), "std_north_m": np.full(n, 0.3), "std_up_m": np.full(n, 0.5),
        "std_yaw_rad": np.full(n, 0.01), "valid": [i != 4 for i in range(n)],
        "roll_pitch_known": np.ones(n, bool)}, schema=schema_of("poses_gnss"))
    info = pa.table({
        "drive": [drive], "sensor": ["HDL-32E"], "T_vehicle_lidar": [T_VEHICLE_LIDAR.reshape(-1).tolist()],
        "origin_lat_deg": [37.5], "origin_lon_deg": [127.0], "origin_h_m": [50.0], "n_scans": [n],
        "n_quarantined": [0], "drive_file": ["drive.yaml"]}, schema=schema_of("drive_info"))
    return {"scans": scans, "poses_gnss": gnss, "drive_info": info}


def test_compute_chunks_overlap_and_edges_match_truth(street_scene):
    truth = _truth(6)
    tables = _tables(street_scene, truth, chunk_of=lambda s: 0 if s < 3 else 1)
    out = {}
    for chunk in (0, 1):
        ctx = make_context("odometry", OdometryParams(), tables, partition=PartitionKey(drive="d0", chunk=chunk))
        from stages.odometry.compute import compute

        out[chunk] = compute(ctx)["edges"]
        assert out[chunk].schema.equals(schema_of("odometry_edges"), check_metadata=False)
    assert out[0]["scan_id"].to_pylist() == [1, 2]
    assert out[1]["scan_id"].to_pylist() == [3, 4, 5]  # edge 2->3 crosses the chunk boundary
    edges = pa.concat_tables([out[0], out[1]])
    for row in edges.to_pylist():
        k = row["scan_id"]
        T_true = se3_inverse(truth[k - 1]) @ truth[k]
        T_est = np.eye(4)
        T_est[:3, :3] = Rotation.from_quat([row["qx"], row["qy"], row["qz"], row["qw"]]).as_matrix()
        T_est[:3, 3] = [row["dx_m"], row["dy_m"], row["dz_m"]]
        D = se3_inverse(T_true) @ T_est
        assert np.linalg.norm(D[:3, 3]) < 0.02, (k, D[:3, 3])
        assert np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec()) < np.deg2rad(0.1)
        assert row["accepted"] and row["fitness"] > 0.7
        assert np.all(np.linalg.eigvalsh(np.reshape(row["information"], (6, 6))) > 0)


def test_compute_rejects_non_rigid_extrinsic(street_scene):
    truth = _truth(2)
    tables = _tables(street_scene, truth, chunk_of=lambda s: 0)
    bad = np.eye(4)
    bad[0, 0] = 2.0
    tables["drive_info"] = tables["drive_info"].set_column(
        2, "T_vehicle_lidar", pa.array([bad.reshape(-1).tolist()], pa.list_(pa.float64(), 16)))
    from stages.odometry.compute import compute

    ctx = make_context("odometry", OdometryParams(), tables, partition=PartitionKey(drive="d0", chunk=0))
    with pytest.raises(FormatError, match="T_vehicle_lidar"):
        compute(ctx)


def test_params_reject_unknown_and_inconsistent_keys():
    with pytest.raises(ValueError):
        OdometryParams(voxel=0.5)
    with pytest.raises(ValueError, match="min_range_m"):
        OdometryParams(prepare={"min_range_m": 90.0, "max_range_m": 80.0})


def test_scans_from_table_same_scans_whatever_the_row_order():
    """Sorted input takes the fast path (no sort); shuffled rows give the same scans, points in file order."""
    from stages.odometry.compute import scans_from_table

    rng = np.random.default_rng(3)
    sizes = {7: 5, 3: 4, 9: 6}
    rows = []
    for sid, n in sizes.items():
        for j in range(n):
            rows.append((sid, sid * 1000, float(sid), float(j), 0.5 * j, 0.0 if sid == 3 else 0.01 * j))
    rows.sort(key=lambda r: r[0])
    table = pa.table({"scan_id": [r[0] for r in rows], "stamp_ns": [r[1] for r in rows],
                      "x_m": pa.array([r[2] for r in rows], pa.float32()),
                      "y_m": pa.array([r[3] for r in rows], pa.float32()),
                      "z_m": pa.array([r[4] for r in rows], pa.float32()),
                      "time_offset_s": pa.array([r[5] for r in rows], pa.float32())})
    shuffled = table.take(rng.permutation(table.num_rows))
    for tab in (table, shuffled):
        scans = scans_from_table(tab)
        assert [s.scan_id for s in scans] == [3, 7, 9]
        assert [len(s.points_lidar_m) for s in scans] == [4, 5, 6]
        assert [s.stamp_ns for s in scans] == [3000, 7000, 9000]
        assert scans[0].time_offset_s is None  # all-zero times: no per-point time
        assert scans[1].points_lidar_m.dtype == np.float64
        assert np.all(scans[0].points_lidar_m[:, 0] == 3.0)
        if tab is table:
            np.testing.assert_allclose(scans[2].points_lidar_m[:, 1], np.arange(6))
        else:
            assert sorted(scans[2].points_lidar_m[:, 1]) == list(range(6))
