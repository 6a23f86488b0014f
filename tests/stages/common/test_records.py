"""Pose rows and drive_info extrinsics: round trips through Arrow, cross-checked against scipy, and named errors."""
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
