"""compute() end to end on in-memory tables: a map drive and a reference drive over the same raycast street."""
from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from pipeline.testing import make_context
from schemas.registry import schema_of
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.records import Trajectory
from stages.posegraph.params import PosegraphParams
from tests.stages.odometry.conftest import build_street_scene, raycast_scan
from tests.stages.posegraph.conftest import perturb

T_VL = se3_from_xyz_rpy(0.0, 0.0, 1.9, 0.0, 0.0, 0.0)


def _drive_tables(name, T_true, scene, rng, t0_s, gnss_offset_m):
    n = len(T_true)
    stamps = ((t0_s + 0.1 * np.arange(n)) * 1e9).astype(np.int64)
    scans, edges = [], []
    for k, T in enumerate(T_true):
        pts = raycast_scan(scene, T @ T_VL, rng).astype(np.float32)
        m = len(pts)
        scans.append(
            pa.table(
                {
                    "drive": [name] * m,
                    "chunk": pa.array([0] * m, pa.int32()),
                    "scan_id": pa.array([k] * m, pa.int64()),
                    "stamp_ns": pa.array([stamps[k]] * m, pa.int64()),
                    "x_m": pts[:, 0],
                    "y_m": pts[:, 1],
                    "z_m": pts[:, 2],
                    "intensity": np.zeros(m, np.float32),
                    "ring": np.zeros(m, np.int16),
                    "time_offset_s": np.zeros(m, np.float32),
                },
                schema=schema_of("scans_raw"),
            )
        )
        if k:
            E = perturb(se3_inverse(T_true[k - 1]) @ T, 2e-4, 3e-3, rng)
            q = Rotation.from_matrix(E[:3, :3]).as_quat()
            edges.append({"drive": name, "chunk": 0, "scan_id": k, "stamp_ns": int(stamps[k]), "dx_m": E[0, 3],
                          "dy_m": E[1, 3], "dz_m": E[2, 3], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3],
                          "fitness": 0.9, "inlier_rmse_m": 0.05,
                          "information": np.diag([2e-4 ** -2] * 3 + [3e-3 ** -2] * 3).reshape(-1).tolist(),
                          "accepted": True})
    G = T_true.copy()
    G[:, :3, 3] += gnss_offset_m + rng.normal(0, 0.05, (n, 3))
    q = Rotation.from_matrix(G[:, :3, :3]).as_quat()
    gnss = pa.table({"drive": [name] * n, "scan_id": pa.array(range(n), pa.int64()), "stamp_ns": stamps,
                     "x_m": G[:, 0, 3], "y_m": G[:, 1, 3], "z_m": G[:, 2, 3], "qx": q[:, 0], "qy": q[:, 1],
                     "qz": q[:, 2], "qw": q[:, 3], "std_east_m": np.full(n, 0.3), "std_north_m": np.full(n, 0.3),
                     "std_up_m": np.full(n, 0.5), "std_yaw_rad": np.full(n, 0.01), "valid": np.ones(n, bool),
                     "roll_pitch_known": np.ones(n, bool)},
                    schema=schema_of("poses_gnss"))
    info = pa.table({"drive": [name], "sensor": ["HDL-32E"], "T_vehicle_lidar": [T_VL.reshape(-1).tolist()],
                     "origin_lat_deg": [37.5], "origin_lon_deg": [127.0], "origin_h_m": [50.0], "n_scans": [n],
                     "n_quarantined": [0], "drive_file": ["drive.yaml"]}, schema=schema_of("drive_info"))
    return pa.concat_tables(scans), pa.Table.from_pylist(edges, schema=schema_of("odometry_edges")), gnss, info


def _map_and_reference_street():
    """A map drive d0 and a reference drive d1 along one raycast street (1 m a scan, 30 scans each), with their
    truths; the two drives see different GNSS biases (0.8 m apart): only loop closures make them agree."""
    scene = build_street_scene(seed=3)
    rng = np.random.default_rng(4)
    T0 = np.array([se3_from_xyz_rpy(-20 + 1.0 * k, 0.3, 0, 0, 0, 0.0) for k in range(30)])
    T1 = np.array([se3_from_xyz_rpy(-19.5 + 1.0 * k, -1.2, 0, 0, 0, 0.02) for k in range(30)])
    d0 = _drive_tables("d0", T0, scene, rng, 0.0, np.array([0.4, -0.3, 0.1]))
    d1 = _drive_tables("d1", T1, scene, rng, 500.0, np.array([-0.4, 0.3, -0.1]))
    tables = {k: pa.concat_tables([a, b]) for k, a, b in zip(("scans", "edges", "poses_gnss", "drive_info"), d0, d1)}
    return tables, T0, T1


def _reference_offset_error_m(opt: pa.Table, T0: np.ndarray, T1: np.ndarray) -> float:
    """How far the reference drive's mean position relative to the map drive's is from the truth's [m]."""
    xy = np.column_stack([opt["x_m"].to_numpy(), opt["y_m"].to_numpy()])
    d = np.array(opt["drive"].to_pylist())
    rel_est = xy[d == "d1"].mean(0) - xy[d == "d0"].mean(0)
    rel_true = T1[:, :2, 3].mean(0) - T0[:, :2, 3].mean(0)
    return float(np.linalg.norm(rel_est - rel_true))


def test_compute_map_and_reference_drive(tmp_path):
    tables, T0, T1 = _map_and_reference_street()
    p = PosegraphParams(loops={"stride_m": 4.0, "reference_stride_m": 4.0}, gnss={"every_s": 0.5})
    ctx = make_context("posegraph", p, tables, settings={"map_drives": ["d0"], "eval_drives": ["d1"]},
                       outputs=("report",), workdir=tmp_path)
    from stages.posegraph.compute import compute

    out = compute(ctx)
    for key, name in (("poses_optimized", "poses_optimized"), ("poses_odometry", "poses_odometry"),
                      ("loop_closures", "loop_closures")):
        assert out[key].schema.equals(schema_of(name), check_metadata=False)
    opt = out["poses_optimized"]
    assert sorted(set(opt["drive"].to_pylist())) == ["d0", "d1"] and opt.num_rows == 60
    loops = out["loop_closures"].to_pylist()
    assert any(r["accepted"] and r["drive_a"] != r["drive_b"] for r in loops)
    # reference drive in the map's frame: its offset to the map drive is right to a few cm
    assert _reference_offset_error_m(opt, T0, T1) < 0.05
    cov = np.stack(opt["cov_xy_yaw"].to_numpy(zero_copy_only=False)).reshape(-1, 3, 3)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    report_dir = ctx.artifact_dir("report")
    T = Trajectory.from_tum(report_dir / "d1_optimized_tum.txt").T
    assert len(T) == 30 and (report_dir / "d0_optimized_kitti.txt").exists()
    report = json.loads((report_dir / "posegraph_report.json").read_text())
    assert report["reference_drives"] == ["d1"] and report["map_drives"] == ["d0"]
    assert (report_dir / "gnss_residuals.png").stat().st_size > 1000


def test_reference_drive_queries_follow_their_own_stride(tmp_path):
    """``loops.reference_stride_m`` spaces the reference drive's loop queries onto the map (the map drives keep
    ``loops.stride_m``): at 10 m on a 30 m drive, the loops' reference scans lie >= 10 m of travel apart (1 m a scan),
    three queries at most; the drive still lands on the map to a few cm."""
    from stages.posegraph.compute import compute

    tables, T0, T1 = _map_and_reference_street()
    p = PosegraphParams(loops={"stride_m": 4.0, "reference_stride_m": 10.0}, gnss={"every_s": 0.5})
    ctx = make_context("posegraph", p, tables, settings={"map_drives": ["d0"], "eval_drives": ["d1"]},
                       outputs=("report",), workdir=tmp_path)
    out = compute(ctx)
    rows = [r for r in out["loop_closures"].to_pylist() if "d1" in (r["drive_a"], r["drive_b"])]
    queries = sorted({r["scan_a"] if r["drive_a"] == "d1" else r["scan_b"] for r in rows})
    assert 1 <= len(queries) <= 3 and np.all(np.diff(queries) >= 10), queries
    assert _reference_offset_error_m(out["poses_optimized"], T0, T1) < 0.05
