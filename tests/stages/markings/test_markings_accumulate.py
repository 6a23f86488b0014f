"""Oracle of the drive-scan cloud (``accumulate.scans_to_enu``): points of a rolling sweep placed at their own time
between the scan's optimized pose and the next land where they were; with the scan-start pose for every point a
city turn puts the last points of a sweep metres off."""
from __future__ import annotations

import numpy as np

from stages.common.geometry import se3_from_xyz_rpy
from stages.markings.accumulate import scans_to_enu, sweep_motion

SPEED_MPS, YAW_RATE_RADPS, SWEEP_S = 10.0, np.radians(29.0), 0.1  # tiny's cruise speed in an intersection turn


def _pose(t_s: float) -> np.ndarray:
    yaw = YAW_RATE_RADPS * t_s
    r = SPEED_MPS / YAW_RATE_RADPS
    return se3_from_xyz_rpy(r * np.sin(yaw), r * (1 - np.cos(yaw)), 0.0, 0.0, 0.0, yaw)


def _sweeps(n_scans: int, rng: np.random.Generator):
    """Ground points seen by a rolling sweep of each scan, the lidar 1.9 m up, shifted and turned on the body."""
    T_vl = se3_from_xyz_rpy(0.4, 0.1, 1.9, 0.0, 0.0, 0.05)
    world, pts, tau, scan = [], [], [], []
    for k in range(n_scans):
        w = np.column_stack([rng.uniform(-25, 25, (300, 2)), np.zeros(300)]) + _pose(k * SWEEP_S)[:3, 3]
        t = rng.uniform(0.0, SWEEP_S, 300)
        for p, ti in zip(w, t):
            pts.append((np.linalg.inv(_pose(k * SWEEP_S + ti) @ T_vl) @ np.r_[p, 1.0])[:3])
        world.append(w), tau.append(t), scan.append(np.full(300, k))
    T = np.stack([_pose(k * SWEEP_S) for k in range(n_scans)])
    stamps = (np.arange(n_scans) * SWEEP_S * 1e9).astype(np.int64)
    return np.concatenate(world), np.array(pts), np.concatenate(tau), np.concatenate(scan), T, stamps, T_vl


def test_points_of_a_rolling_sweep_land_where_they_were():
    world, pts, tau, scan, T, stamps, T_vl = _sweeps(4, np.random.default_rng(1))
    ids = np.arange(len(T))
    raw, keep = scans_to_enu(pts, scan, ids, T, T_vl, min_range_m=0.0, max_range_m=1e9)
    placed, keep2 = scans_to_enu(pts, scan, ids, T, T_vl, min_range_m=0.0, max_range_m=1e9, time_offset_s=tau,
                                 pose_stamps_ns=stamps)
    assert keep.all() and keep2.all()
    err_raw = np.linalg.norm(raw - world, axis=1)
    err = np.linalg.norm(placed - world, axis=1)
    assert err_raw.max() > 1.0  # the scan-start pose for every point: metres off in a turn
    assert err.max() < 0.01  # linear translation on an arc: millimetres
    # the last scan has no next pose: its previous step stands in (the same motion here)
    assert np.linalg.norm(placed[scan == 3] - world[scan == 3], axis=1).max() < 0.01


def test_sweep_motion_uses_the_previous_step_across_a_gap_and_none_for_a_single_pose():
    T = np.stack([_pose(k * SWEEP_S) for k in (0, 1, 2, 5, 6)])
    ids = np.array([0, 1, 2, 5, 6])
    stamps = (ids * SWEEP_S * 1e9).astype(np.int64)
    D, dt = sweep_motion(T, stamps, ids)
    np.testing.assert_allclose(D[0], np.linalg.inv(T[0]) @ T[1], atol=1e-12)
    np.testing.assert_allclose(D[2], D[1])  # before the gap and at the end: the step before
    np.testing.assert_allclose(D[4], D[3])
    assert np.allclose(dt, SWEEP_S)
    D1, dt1 = sweep_motion(T[:1], stamps[:1], ids[:1])
    assert dt1[0] == 0.0 and np.allclose(D1[0], np.eye(4))
