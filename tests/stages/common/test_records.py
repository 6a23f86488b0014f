"""Pose rows, drive_info extrinsics and scans_raw rows: round trips through Arrow, cross-checked against scipy,
and named errors."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.errors import FormatError
from stages.common.records import INCREMENT_COLUMNS, Extrinsics, Trajectory, pose_columns, pose_matrices, yaw_rad


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0, 100, (n, 3))
    return T


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 30), st.integers(0, 2**31))
def test_pose_rows_round_trip(n, seed):
    T = _poses(n, seed)
    table = pa.table(pose_columns(T))
    assert np.allclose(pose_matrices(table), T, atol=1e-12)
    inc = pa.table(pose_columns(T, position=INCREMENT_COLUMNS))
    assert np.allclose(pose_matrices(inc, position=INCREMENT_COLUMNS), T, atol=1e-12)


def test_yaw_and_row_selection_match_scipy():
    yaw = np.array([-3.0, -1.0, 0.0, 0.5, 3.1])
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("ZYX", np.column_stack([yaw, 0.01 * yaw, -0.02 * yaw])).as_matrix()
    table = pa.table(pose_columns(T))
    assert np.allclose(yaw_rad(table), yaw)
    assert np.allclose(yaw_rad(table, np.array([4, 0])), yaw[[4, 0]])
    assert np.allclose(pose_matrices(table, np.array([3, 1])), T[[3, 1]])


def test_trajectory_selects_the_drive_and_sorts_by_scan():
    T = _poses(6, 3)
    cols = {"drive": ["a", "b"] * 3, "scan_id": [5, 1, 3, 2, 4, 0], "stamp_ns": [50, 10, 30, 20, 40, 0],
            **pose_columns(T)}
    traj = Trajectory.from_table(pa.table(cols), "a")
    assert traj.scan_id.tolist() == [3, 4, 5] and traj.stamp_ns.tolist() == [30, 40, 50]
    assert np.allclose(traj.T, T[[2, 4, 0]])
    back = Trajectory.from_table(pa.table(traj.to_columns()), "a")
    assert np.allclose(back.T, traj.T) and back.scan_id.tolist() == traj.scan_id.tolist()
    assert np.allclose(traj.yaw_rad, Rotation.from_matrix(traj.T[:, :3, :3]).as_euler("ZYX")[:, 0])


def test_tum_files_read_back_what_was_written_and_malformed_ones_are_named(tmp_path):
    """``write_tum`` (9 decimals) -> ``Trajectory.from_tum``: poses within 1e-9 m / rad, GPS-epoch stamps to the
    nanosecond, one scan per row; a wrong column count or a word in a line is a FormatError naming file and line."""
    from stages.common.geometry import write_tum

    T = _poses(7, 4)
    stamps_ns = 1_400_000_000_000_000_000 + np.arange(7, dtype=np.int64) * 100_000_123
    path = tmp_path / "truth_tum.txt"
    write_tum(path, stamps_ns * 1e-9, T, header="frame: ENU lat_deg=37.5 lon_deg=127.0 h_m=40.0")
    traj = Trajectory.from_tum(path, "d0")
    assert traj.drive == "d0" and traj.scan_id.tolist() == list(range(7))
    assert np.abs(traj.stamp_ns - stamps_ns).max() <= 256  # float64 seconds at 1.4e9 s: 0.24 us steps
    np.testing.assert_allclose(traj.T[:, :3, 3], T[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(traj.T[:, :3, :3], T[:, :3, :3], atol=1e-8)
    bad = tmp_path / "bad.txt"
    bad.write_text("0.0 1 2 3 0 0 0\n")
    with pytest.raises(FormatError, match=r"bad.txt: line 1: 7 values; expected 8 \(t x y z qx qy qz qw\)"):
        Trajectory.from_tum(bad)
    bad.write_text("# a header\n0.0 1 2 3 0 0 0 one\n")
    with pytest.raises(FormatError, match="bad.txt: line 2: .* not a number"):
        Trajectory.from_tum(bad)


def test_extrinsics_round_trip_and_named_errors():
    T = _poses(2, 9)
    info = pa.table({"drive": ["d0", "d1"], "T_vehicle_lidar": [Extrinsics.to_column(t) for t in T]})
    ext = Extrinsics.from_table(info)
    assert np.array_equal(ext.of("d1"), T[1])
    with pytest.raises(FormatError, match="no row for drive 'd2'.*'d0', 'd1'"):
        ext.of("d2")
    with pytest.raises(FormatError, match="drive 'x'.*16 values.*got 3"):
        Extrinsics.from_table(pa.table({"drive": ["x"], "T_vehicle_lidar": [[1.0, 2.0, 3.0]]}))
    sheared = np.eye(4)
    sheared[0, 1] = 0.3
    with pytest.raises(FormatError, match="drive 'y'.*not a rigid"):
        Extrinsics.from_table(pa.table({"drive": ["y"], "T_vehicle_lidar": [Extrinsics.to_column(sheared)]}))
    with pytest.raises(FormatError, match="4x4"):
        Extrinsics.to_column(np.eye(3))


def _scan_points(n_scans: int, seed: int):
    from stages.common.records import RawScanPoints

    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 40, n_scans)
    n = int(counts.sum())
    ids = np.arange(n_scans, dtype=np.int64) * 3 + 5
    return RawScanPoints(np.repeat(ids, counts), np.repeat(ids * 100_000_000 + 7, counts),
                         rng.normal(0, 30, (n, 3)).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32),
                         rng.integers(0, 32, n).astype(np.int16), rng.uniform(0, 0.1, n).astype(np.float32)), counts


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 12), st.integers(0, 2**31))
def test_scans_raw_rows_round_trip(n_scans, seed):
    from schemas import SCHEMAS
    from stages.common.records import decode_scans_raw, encode_scans_raw

    p, counts = _scan_points(n_scans, seed)
    table = encode_scans_raw("d0", 3, p)
    assert table.schema.equals(SCHEMAS["scans_raw"], check_metadata=True)
    assert table["chunk"].to_pylist() == [3] * len(p) and set(table["drive"].to_pylist()) <= {"d0"}
    back = decode_scans_raw(table)
    for name in ("scan_id", "stamp_ns", "xyz_lidar_m", "intensity", "ring", "time_offset_s"):
        assert np.array_equal(getattr(back, name), getattr(p, name)), name
    ids, bounds = back.scan_rows()
    kept = counts > 0
    assert np.array_equal(ids, (np.arange(n_scans) * 3 + 5)[kept]) and np.array_equal(np.diff(bounds), counts[kept])
    for sid, r in zip(np.arange(n_scans) * 3 + 5, back.rows_of(np.arange(n_scans) * 3 + 5)):
        assert np.all(back.scan_id[r] == sid) and r.stop - r.start == counts[(sid - 5) // 3]


def test_scans_raw_decode_groups_shuffled_rows_by_scan_stably_and_keeps_them_in_table_order_on_request():
    from stages.common.records import decode_scans_raw, encode_scans_raw

    p, _ = _scan_points(6, 11)
    table = encode_scans_raw("d0", 0, p)
    perm = np.random.default_rng(2).permutation(table.num_rows)
    shuffled = table.take(pa.array(perm))
    back = decode_scans_raw(shuffled)
    stable = np.argsort(p.scan_id[perm], kind="stable")
    assert np.array_equal(back.xyz_lidar_m, p.xyz_lidar_m[perm][stable])
    assert np.array_equal(back.scan_id, p.scan_id)  # grouped by scan again
    as_read = decode_scans_raw(shuffled.select(["x_m", "y_m", "z_m", "intensity"]), by_scan=False)
    assert np.array_equal(as_read.xyz_lidar_m, p.xyz_lidar_m[perm]) and as_read.ring is None
    assert np.array_equal(as_read.intensity, p.intensity[perm])


def test_malformed_scans_raw_rows_are_named_errors():
    from stages.common.records import RawScanPoints, decode_scans_raw, encode_scans_raw

    p, _ = _scan_points(4, 5)
    table = encode_scans_raw("d0", 0, p)
    stamps = table["stamp_ns"].to_numpy().copy()
    stamps[-1] += 1  # the last scan's last point claims another scan start
    with pytest.raises(FormatError, match=rf"scan {int(p.scan_id[-1])}: stamp_ns"):
        decode_scans_raw(table.set_column(table.schema.get_field_index("stamp_ns"), "stamp_ns", pa.array(stamps)))
    with pytest.raises(FormatError, match="z_m missing"):
        decode_scans_raw(table.select(["scan_id", "x_m", "y_m"]))
    with pytest.raises(FormatError, match="no scan_id column"):
        decode_scans_raw(table.select(["x_m", "y_m", "z_m"]))
    with pytest.raises(FormatError, match="ring must hold"):
        encode_scans_raw("d0", 0, RawScanPoints(p.scan_id, p.stamp_ns, p.xyz_lidar_m, p.intensity, p.ring[:-1]))
