"""The stage adapter on in-memory tables: schemas in, eval_epochs + report artifacts out."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation

from fixtures.evaluate import (
    ground_ring_scan,
    observe_corners,
    paint_markings,
    relative_increments,
    road_trajectory,
    roadside_corners,
)
from pipeline.testing import make_context
from schemas import schema_of
from stages.common.geodesy import EnuOrigin
from stages.common.geometry import se3_from_xyz_rpy, write_tum
from stages.common.trajectory_frame import frame_header
from stages.evaluate import compute as compute_mod
from stages.evaluate.params import EvaluateParams

N, CELL, DRIVE = 40, 0.1, "drive_1"
MAP_ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)


def _table(name: str, cols: dict) -> pa.Table:
    schema = schema_of(name)
    return pa.table({f.name: pa.array(cols[f.name], type=f.type) for f in schema}, schema=schema)


def _quat(yaw: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("z", np.asarray(yaw)[:, None]).as_quat()


class FakeMap:
    """Stands in for mapformat.loader.MapReader (north-up marking rasters, corner tables)."""

    def __init__(self, corners, dirs, mask, raster_origin):
        self.corners, self.dirs, self.mask, self.raster_origin = corners, dirs, mask, raster_origin
        self.cell_m, self.path, self.version = CELL, Path("fake/v0001"), 1
        self.origin, self.manifest = MAP_ORIGIN, {"version": 1}

    def corners_in_bbox(self, e0, n0, e1, n1):
        n = len(self.corners)
        return pa.table({"east_m": self.corners[:, 0], "north_m": self.corners[:, 1], "theta1_rad": self.dirs[:, 0],
                         "theta2_rad": self.dirs[:, 1], "cov_ee_m2": np.full(n, 1e-3), "cov_en_m2": np.zeros(n),
                         "cov_nn_m2": np.full(n, 1e-3)})

    @staticmethod
    def covariances(t):
        ee, en, nn = (t[c].to_numpy() for c in ("cov_ee_m2", "cov_en_m2", "cov_nn_m2"))
        return np.stack([np.stack([ee, en], -1), np.stack([en, nn], -1)], -2)

    def marking_window(self, e0, n0, e1, n1):
        return np.flipud(self.mask), self.raster_origin, CELL  # the loader's convention: row 0 = north edge

    def observed_window(self, e0, n0, e1, n1):  # the survey saw the whole raster
        return np.ones_like(self.mask), self.raster_origin, CELL


@pytest.fixture()
def stage_context(tmp_path, monkeypatch):
    rng = np.random.default_rng(8)
    truth = road_trajectory(N)
    mask, origin = paint_markings(120.0, 40.0, CELL, road_y_m=20.0, crosswalks_x_m=(35.0,))
    corners, dirs = roadside_corners(120.0, 20.0, rng)
    stamps = 10**12 + np.arange(N) * 100_000_000
    T_vl = np.eye(4)
    T_vl[:3, 3] = [0.5, 0.0, 1.8]  # lidar 0.5 m ahead of the vehicle origin, 1.8 m up
    truth_lidar = truth + np.column_stack([0.5 * np.cos(truth[:, 2]), 0.5 * np.sin(truth[:, 2]), np.zeros(N)])
    ep, xy, cov, cdirs = observe_corners(truth_lidar, corners, dirs, rng)
    inc = relative_increments(truth)
    q = _quat(truth[:, 2])
    ones, zeros = np.ones(N), np.zeros(N)
    tables = {
        "poses_gnss": _table("poses_gnss", {"drive": [DRIVE] * N, "scan_id": np.arange(N), "stamp_ns": stamps,
                                            "x_m": truth[:, 0] + 0.3, "y_m": truth[:, 1] - 0.2, "z_m": zeros,
                                            "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
                                            "std_east_m": 0.5 * ones, "std_north_m": 0.5 * ones, "std_up_m": ones,
                                            "std_yaw_rad": 0.01 * ones, "valid": np.ones(N, bool),
                                            "roll_pitch_known": np.ones(N, bool)}),
        "drive_info": _table("drive_info", {"drive": [DRIVE], "sensor": ["sim"], "T_vehicle_lidar": [T_vl.ravel()],
                                            "origin_lat_deg": [0.0], "origin_lon_deg": [0.0], "origin_h_m": [0.0],
                                            "n_scans": [N], "n_quarantined": [0], "drive_file": ["d.yaml"]}),
        "odometry": _table("odometry_raw", {"drive": [DRIVE] * N, "stamp_ns": stamps, "speed_mps": 8.0 * ones,
                                            "yaw_rate_radps": np.gradient(np.unwrap(truth[:, 2])) * 10.0}),
        "edges": _table("odometry_edges", {
            "drive": [DRIVE] * (N - 1), "chunk": np.zeros(N - 1, int), "scan_id": np.arange(1, N),
            "stamp_ns": stamps[1:], "dx_m": inc[1:, 0], "dy_m": inc[1:, 1], "dz_m": zeros[1:],
            **dict(zip(("qx", "qy", "qz", "qw"), _quat(inc[1:, 2]).T)), "fitness": ones[1:],
            "inlier_rmse_m": 0.05 * ones[1:], "information": [np.eye(6).ravel()] * (N - 1),
            "accepted": np.ones(N - 1, bool)}),
        "corners": _table("corners_per_scan", {
            "drive": [DRIVE] * len(ep), "chunk": np.zeros(len(ep), int), "scan_id": ep, "stamp_ns": stamps[ep],
            "corner_idx": np.zeros(len(ep), int), "x_m": xy[:, 0], "y_m": xy[:, 1], "theta1_rad": cdirs[:, 0],
            "theta2_rad": cdirs[:, 1], "cov_xx_m2": cov[:, 0, 0], "cov_xy_m2": cov[:, 0, 1], "cov_yy_m2": cov[:, 1, 1],
            "n_layers": np.full(len(ep), 8), "range_m": np.hypot(xy[:, 0], xy[:, 1]),
            "interior_angle_rad": np.full(len(ep), np.pi / 2), "convex": np.ones(len(ep), bool),
            "time_offset_s": np.zeros(len(ep))}),
        "reference": _table("poses_optimized", {
            "drive": [DRIVE] * N, "scan_id": np.arange(N), "stamp_ns": stamps, "x_m": truth[:, 0], "y_m": truth[:, 1],
            "z_m": zeros, "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
            "cov_xy_yaw": [np.eye(3).ravel() * 1e-4] * N}),
        "map": pa.table({"map_name": ["t"], "version": [1], "path": ["fake/v0001"]}),
    }
    scans = []
    for k in range(N):
        xyz, inten, ring = ground_ring_scan(truth[k], mask, origin, CELL, rng, lidar_height_m=1.8,
                                            azimuth_step_deg=0.4)
        xyz[:, 0] -= 0.5  # points were generated about the vehicle origin; express them in the lidar frame
        n = len(xyz)
        scans.append({"drive": [DRIVE] * n, "chunk": np.full(n, k // 20), "scan_id": np.full(n, k),
                      "stamp_ns": np.full(n, stamps[k]), "x_m": xyz[:, 0], "y_m": xyz[:, 1], "z_m": xyz[:, 2],
                      "intensity": inten, "ring": ring, "time_offset_s": np.zeros(n)})
    tables["scans"] = pa.concat_tables([_table("scans_raw", s) for s in scans])
    truth_path = tmp_path / "truth.txt"
    write_tum(truth_path, stamps * 1e-9, np.stack([se3_from_xyz_rpy(x, y, 0, 0, 0, a) for x, y, a in truth]),
              header=frame_header(MAP_ORIGIN))
    monkeypatch.setattr(compute_mod, "open_published_map", lambda ctx: FakeMap(corners, dirs, mask, origin))
    ctx = make_context("evaluate", EvaluateParams(mcl={"n_particles": 300}), tables, partition=compute_mod.PartitionKey(
        drive=DRIVE), settings={"references": {DRIVE: str(truth_path)}, "eval_drives": [DRIVE]},
        outputs=("report",), workdir=tmp_path)
    return ctx, truth


def _rerun(ctx, tmp_path, **changes):
    """The same context with other settings or params (a fresh artifact directory)."""
    from dataclasses import replace

    out = tmp_path / f"run{len(list(tmp_path.glob('run*')))}"
    data = ctx.params.model_dump()
    for key, value in changes.pop("params", {}).items():  # a section's fields merge into it
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    return replace(ctx, params=type(ctx.params).model_validate(data),
                   settings={**ctx.settings, **changes.pop("settings", {})}, artifact_dirs={"report": out})


def test_compute_writes_epochs_and_report(stage_context):
    ctx, truth = stage_context
    out = compute_mod.compute(ctx)
    table = out["epochs"]
    assert table.schema.equals(schema_of("eval_epochs"), check_metadata=False)
    report_dir = ctx.artifact_dir("report")
    doc = json.loads((report_dir / "metrics.json").read_text())
    assert doc["primary_reference"] == "map"
    ekf = doc["methods"]["ekf"]
    assert ekf["epochs"] == N and ekf["rms_2d_m"] < 0.1
    assert doc["methods"]["mcl"]["absolute"]["rms_2d_m"] < 0.3
    assert ekf["absolute"]["rms_2d_m"] == pytest.approx(ekf["map_relative"]["rms_2d_m"], abs=1e-6)  # same here
    for name in ("report.html", "epochs.parquet", "ekf_tum.txt", "mcl_tum.txt", "rtk_ins_tum.txt", "icp_dr_tum.txt"):
        assert (report_dir / name).is_file(), name
    assert max(table.filter(pa.compute.equal(table["method"], "ekf"))["n_associated"].to_pylist()) >= 1


def test_icp_increments_fall_back_on_wheel_when_failed_or_off_in_heading():
    """Failed edges (NaN) always take the wheel/gyro increment; an edge whose heading change is off the gyro's by
    more than the gate does too (also across the +-pi wrap); the rest keep ICP's."""
    from stages.evaluate.compute import fall_back_on_wheel

    wheel = np.array([[0.6, 0.0, 0.0], [0.6, 0.01, 0.001], [0.6, 0.0, np.pi - 1e-4], [0.6, 0.0, 0.0],
                      [0.6, 0.0, 0.0]])
    icp = np.array([[0.61, 0.0, 0.0005], [0.59, 0.0, 0.001 + np.deg2rad(0.2)], [0.6, 0.0, -np.pi + 1e-4],
                    [np.nan] * 3, [0.62, 0.0, np.deg2rad(-0.04)]])
    out = fall_back_on_wheel(icp, wheel, np.deg2rad(0.05))
    np.testing.assert_array_equal(out[[0, 2, 4]], icp[[0, 2, 4]])  # within the gate (row 2: 2e-4 rad over the wrap)
    np.testing.assert_array_equal(out[[1, 3]], wheel[[1, 3]])
    only_failed = fall_back_on_wheel(icp, wheel, 0.0)
    np.testing.assert_array_equal(only_failed[[0, 1, 2, 4]], icp[[0, 1, 2, 4]])
    np.testing.assert_array_equal(only_failed[3], wheel[3])
    assert np.isnan(icp[3]).all()  # the input is not modified


def test_the_ekf_uses_the_correlation_the_map_states_unless_told_otherwise():
    from types import SimpleNamespace

    p = EvaluateParams(ekf={"map": {"corr_share": 0.1, "corr_length_m": 20.0}})
    stated = SimpleNamespace(corner_error_correlation=(0.73, 47.7))
    used = compute_mod.with_map_correlation(p, stated)
    assert (used.ekf.map.corr_share, used.ekf.map.corr_length_m) == (0.73, 47.7)
    assert used.ekf.map.corr_share == 0.73 and used.ekf.map.corr_length_m == 47.7
    assert compute_mod.with_map_correlation(p, SimpleNamespace(corner_error_correlation=None)) is p
    own = p.model_copy(update={"ekf": p.ekf.replace(map={"corr_source": "params"})})
    assert compute_mod.with_map_correlation(own, stated) is own
