"""Oracles for the road plane: a known tilted plane with clutter is recovered; aligning two scans' planes
restores the height, roll and pitch of a relative pose without touching its heading; no ground -> None."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.ground_plane import align_ground_planes, fit_ground_plane, ground_mask

T_VEHICLE_LIDAR = se3_from_xyz_rpy(0.0, 0.0, 1.9, 0.0, 0.0, 0.0)


def _scene_lidar(rng, pitch_rad=0.02, roll_rad=-0.01, n_ground=20000):
    """Road points on a plane tilted by (roll, pitch) under the sensor, plus a car and a sidewalk; lidar frame."""
    xy = rng.uniform(-25, 25, (n_ground, 2))
    z = np.tan(pitch_rad) * xy[:, 0] - np.tan(roll_rad) * xy[:, 1] + rng.normal(0, 0.02, n_ground)
    road = np.column_stack([xy, z])
    car = np.column_stack([rng.uniform(4, 8.5, 3000), rng.uniform(2, 4, 3000), rng.uniform(0.6, 1.5, 3000)])
    walk = np.column_stack([rng.uniform(-25, 25, 2000), rng.uniform(7, 9, 2000), 0.15 + rng.normal(0, 0.01, 2000)])
    pts_vehicle = np.vstack([road, car, walk])
    return pts_vehicle - T_VEHICLE_LIDAR[:3, 3], len(road)


def test_fit_recovers_a_tilted_road_under_clutter():
    rng = np.random.default_rng(3)
    pts, n_road = _scene_lidar(rng)
    plane = fit_ground_plane(pts, T_VEHICLE_LIDAR)
    assert plane is not None
    expected = np.array([-np.tan(0.02), np.tan(-0.01), 1.0])
    expected /= np.linalg.norm(expected)
    assert np.degrees(np.arccos(plane.normal @ expected)) < 0.05
    assert abs(plane.offset_m - 1.9 * expected[2]) < 0.01  # the sensor sits 1.9 m above the road
    mask = ground_mask(pts, plane, 0.25)
    assert mask[:n_road].mean() > 0.99 and not mask[n_road:n_road + 3000].any()  # the car is structure


def test_no_visible_ground_gives_none():
    rng = np.random.default_rng(4)
    wall = np.column_stack([np.full(5000, 6.0), rng.uniform(-10, 10, 5000), rng.uniform(0, 8, 5000)])
    assert fit_ground_plane(wall, T_VEHICLE_LIDAR) is None


def test_aligning_planes_fixes_height_roll_pitch_and_keeps_heading():
    rng = np.random.default_rng(5)
    pts, _ = _scene_lidar(rng, pitch_rad=0.0, roll_rad=0.0)
    T_true = se3_from_xyz_rpy(1.0, 0.1, 0.0, 0.0, 0.0, np.radians(2.0))  # target <- source, on flat road
    src = (pts - T_true[:3, 3]) @ T_true[:3, :3]  # the same road seen from the moved sensor
    p_src, p_tgt = fit_ground_plane(src, T_VEHICLE_LIDAR), fit_ground_plane(pts, T_VEHICLE_LIDAR)
    T_bad = T_true @ se3_from_xyz_rpy(0.0, 0.0, 0.12, 0.01, -0.015, 0.0)  # wrong height, roll, pitch
    T_fixed = align_ground_planes(T_bad, p_src, p_tgt)
    D = se3_inverse(T_true) @ T_fixed
    assert abs(D[2, 3]) < 0.005 and np.linalg.norm(D[:2, 3]) < 0.01
    roll, pitch = Rotation.from_matrix(D[:3, :3]).as_euler("xyz")[:2]
    assert abs(roll) < 2e-4 and abs(pitch) < 2e-4
    yaw_bad = Rotation.from_matrix(T_bad[:3, :3]).as_euler("zyx")[0]
    yaw_fixed = Rotation.from_matrix(T_fixed[:3, :3]).as_euler("zyx")[0]
    assert abs(yaw_fixed - yaw_bad) < 2e-4
