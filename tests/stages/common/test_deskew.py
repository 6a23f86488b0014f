"""Oracles for the one deskew module: the kernel undoes known per-point poses; the wheel source is the vehicle's
arc seen through T_vehicle_lidar; the transform source agrees with the arc (and with gtsam's SE(3) exponential
for any constant twist) in rotation exactly and in translation up to the chord's sagitta |w x v| P^2 / 8."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.common.deskew import (
    SweepMotion,
    deskew_points,
    deskew_with_transform,
    deskew_with_wheel,
    interpolate_transform,
    motion_from_transform,
    motion_from_wheel,
    rotate_about_axis,
    vehicle_motion_xy_yaw,
)
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse

PERIOD_S = 0.1


def _random_poses(rng, n):
    return np.array([gtsam.Pose3.Expmap(np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 2.0, 3)]).matrix()
                     for _ in range(n)])


def test_the_kernel_undoes_per_point_poses():
    rng = np.random.default_rng(1)
    T = _random_poses(rng, 300)
    p_start = rng.uniform(-40, 40, (300, 3))
    p_t = np.einsum("nji,nj->ni", T[:, :3, :3], p_start - T[:, :3, 3])  # seen from T_start_t: T^-1 p_start
    out = deskew_points(p_t, SweepMotion(T[:, :3, :3], T[:, :3, 3]))
    np.testing.assert_allclose(out, p_start, atol=1e-12)
    assert np.abs(p_t - p_start).max() > 1.0  # the poses were not the identity


def test_the_transform_source_starts_at_the_identity_ends_at_the_transform_and_clips():
    T = se3_from_xyz_rpy(1.1, -0.2, 0.05, 0.01, -0.02, 0.07)
    m = interpolate_transform(T, np.array([0.0, 1.0]))
    np.testing.assert_allclose(m.R[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(m.t_m[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(m.R[1], T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(m.t_m[1], T[:3, 3], atol=1e-12)
    far = motion_from_transform(np.array([5.0 * PERIOD_S]), T, PERIOD_S)  # clipped to twice the motion
    np.testing.assert_allclose(far.t_m[0], interpolate_transform(T, np.array([2.0])).t_m[0], atol=1e-15)
    pts = np.ones((3, 3))
    np.testing.assert_array_equal(deskew_with_transform(pts, np.zeros(3), T, 0.0), pts)  # no period: unchanged
    assert deskew_with_transform(np.zeros((0, 3)), np.zeros(0), T, PERIOD_S).shape == (0, 3)


def test_the_wheel_source_is_the_vehicle_arc_seen_through_the_extrinsics():
    rng = np.random.default_rng(2)
    T_vl = se3_from_xyz_rpy(0.9, -0.1, 1.7, 0.02, -0.03, 0.4)
    t = rng.uniform(0, PERIOD_S, 50)
    m = motion_from_wheel(t, 12.0, 0.5, T_vl)
    x, y, yaw = vehicle_motion_xy_yaw(t, 12.0, 0.5)
    for k in range(len(t)):  # 4x4 matrices, one point at a time: T_lidar0_lidark = T_vl^-1 T_v0_vk T_vl
        T = se3_inverse(T_vl) @ se3_from_xyz_rpy(x[k], y[k], 0.0, 0.0, 0.0, yaw[k]) @ T_vl
        np.testing.assert_allclose(m.R[k], T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(m.t_m[k], T[:3, 3], atol=1e-12)


def _arc_end(speed_mps, yaw_rate_radps, T_vl):
    end = motion_from_wheel(np.array([PERIOD_S]), speed_mps, yaw_rate_radps, T_vl)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = end.R[0], end.t_m[0]
    return T


def test_a_straight_constant_twist_gives_the_same_motion_from_both_sources():
    T_vl = se3_from_xyz_rpy(0.9, -0.1, 1.7, 0.02, -0.03, 0.4)
    t = np.linspace(0, PERIOD_S, 101)
    wheel = motion_from_wheel(t, 14.0, 0.0, T_vl)
    chord = motion_from_transform(t, _arc_end(14.0, 0.0, T_vl), PERIOD_S)
    np.testing.assert_allclose(chord.R, wheel.R, atol=1e-12)
    np.testing.assert_allclose(chord.t_m, wheel.t_m, atol=1e-12)


@pytest.mark.parametrize("speed_mps, yaw_rate_radps", [(10.0, 0.3), (15.0, 1.0), (5.0, -0.6)])
def test_a_planar_turn_differs_between_the_sources_by_the_chord_sagitta(speed_mps, yaw_rate_radps):
    """Same heading at every instant; positions on the chord (transform) vs the arc (wheel), apart by at most
    L * theta / 8 (3.75 mm at 10 m/s, 0.3 rad/s over 0.1 s), reached at mid-sweep."""
    t = np.linspace(0, PERIOD_S, 1001)
    wheel = motion_from_wheel(t, speed_mps, yaw_rate_radps)
    chord = motion_from_transform(t, _arc_end(speed_mps, yaw_rate_radps, None), PERIOD_S)
    np.testing.assert_allclose(chord.R, wheel.R, atol=1e-12)
    gap_m = np.linalg.norm(chord.t_m - wheel.t_m, axis=1)
    sagitta_m = speed_mps * PERIOD_S * abs(yaw_rate_radps) * PERIOD_S / 8
    assert sagitta_m * 0.99 < gap_m.max() <= sagitta_m * 1.0001
    assert abs(t[np.argmax(gap_m)] - PERIOD_S / 2) < 0.01 * PERIOD_S
    np.testing.assert_allclose(gap_m[[0, -1]], 0.0, atol=1e-12)


def test_the_transform_source_follows_any_constant_twist_up_to_the_sagitta():
    """gtsam's Pose3.Expmap(s xi) is the constant-twist path; the interpolation keeps its rotation exactly and
    leaves the translation within |w x v| / 8 of it (xi per sweep: w rotation, v translation)."""
    rng = np.random.default_rng(3)
    s = np.linspace(0, 1, 201)
    for _ in range(5):
        xi = np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 1.0, 3)]
        screw = np.array([gtsam.Pose3.Expmap(si * xi).matrix() for si in s])
        chord = motion_from_transform(s * PERIOD_S, screw[-1], PERIOD_S)
        np.testing.assert_allclose(chord.R, screw[:, :3, :3], atol=1e-12)
        bound_m = np.linalg.norm(np.cross(xi[:3], xi[3:])) / 8
        gap_m = np.linalg.norm(chord.t_m - screw[:, :3, 3], axis=1).max()
        assert bound_m * 0.99 < gap_m <= bound_m * 1.0001


def test_deskewing_a_swept_scan_recovers_the_scene_within_the_sagitta():
    """Points of a static scene seen along a constant-twist sweep (gtsam exponential), deskewed with the
    sweep's start->end transform: back within the sagitta; the raw scan was off by decimetres."""
    rng = np.random.default_rng(5)
    xi = np.r_[0.0, 0.0, 0.05, 1.0, 0.1, 0.0]
    p_start = rng.uniform(-30, 30, size=(2000, 3))
    t = rng.uniform(0, PERIOD_S, 2000)
    p_t = np.empty_like(p_start)
    for i, ti in enumerate(t):  # test oracle, not a hot path
        T_inv = se3_inverse(gtsam.Pose3.Expmap(ti / PERIOD_S * xi).matrix())
        p_t[i] = T_inv[:3, :3] @ p_start[i] + T_inv[:3, 3]
    out = deskew_with_transform(p_t, t, gtsam.Pose3.Expmap(xi).matrix(), PERIOD_S)
    assert np.abs(out - p_start).max() <= np.linalg.norm(np.cross(xi[:3], xi[3:])) / 8 * 1.0001
    assert np.abs(p_t - p_start).max() > 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_point_by_point_appliers_equal_the_per_point_matrices(seed):
    """``deskew_with_wheel`` and ``deskew_with_transform`` apply their motion without an (N,3,3) matrix per point;
    they equal ``deskew_points`` of ``motion_from_wheel`` / ``motion_from_transform`` (sampled odometry, constant
    twist, any transform, times past the period that the transform source clips)."""
    rng = np.random.default_rng(seed)
    T_vl = se3_from_xyz_rpy(*rng.normal(0, 1.0, 3), *rng.normal(0, 0.05, 3))
    p = rng.uniform(-60, 60, (5000, 3))
    t = rng.uniform(-0.01, 2.5 * PERIOD_S, 5000)
    odo_t = np.linspace(-0.05, 0.4, 46)
    speed, rate = rng.uniform(0, 20, 46), rng.normal(0, 0.5, 46)
    np.testing.assert_allclose(deskew_with_wheel(p, t.clip(0), speed, rate, T_vl, odo_time_s=odo_t),
                               deskew_points(p, motion_from_wheel(t.clip(0), speed, rate, T_vl, odo_time_s=odo_t)),
                               atol=1e-9)
    np.testing.assert_allclose(deskew_with_wheel(p, t, 13.0, -0.7, T_vl),
                               deskew_points(p, motion_from_wheel(t, 13.0, -0.7, T_vl)), atol=1e-9)
    T = gtsam.Pose3.Expmap(np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 1.5, 3)]).matrix()
    np.testing.assert_allclose(deskew_with_transform(p, t, T, PERIOD_S),
                               deskew_points(p, motion_from_transform(t, T, PERIOD_S)), atol=1e-9)
    np.testing.assert_array_equal(rotate_about_axis(p, np.zeros(3), t), p)  # no rotation: the points
