"""Motion compensation: a scan rolled while the sensor moves (ray-cast per firing) is straightened again."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.corners import Scene, box_building, cast_scan
from stages.common.deskew import deskew_with_wheel, integrate_odometry_xy_yaw, vehicle_motion_xy_yaw
from stages.corners.core import extract_corners

BOX = box_building((0.0, 0.0), (12.0, 8.0), yaw_rad=0.4, height_m=14.0)
POSE = (22.0 * np.cos(0.4 + np.pi / 4), 22.0 * np.sin(0.4 + np.pi / 4), -2.0)


def corner_errors_m(corners, pose):
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    xy = np.column_stack([x + c * corners.x_m - s * corners.y_m, y + s * corners.x_m + c * corners.y_m])
    return np.linalg.norm(xy[:, None] - BOX.footprint_xy_m[None], axis=2).min(axis=1)


def test_deskew_is_the_identity_at_rest_and_inverts_a_known_motion():
    rng = np.random.default_rng(0)
    p0 = rng.uniform(-30, 30, (500, 3))
    t = rng.uniform(0, 0.1, 500)
    np.testing.assert_allclose(deskew_with_wheel(p0, t, 0.0, 0.0), p0, atol=1e-12)
    T_vl = np.eye(4)
    T_vl[:3, 3] = [0.8, 0.1, 1.7]
    # forward model: the point p0 (lidar frame at t=0) seen from the lidar at time t
    x, y, yaw = vehicle_motion_xy_yaw(t, 12.0, 0.5)
    pv0 = p0 + T_vl[:3, 3]
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = pv0[:, 0] - x, pv0[:, 1] - y
    pv_t = np.column_stack([c * dx + s * dy, -s * dx + c * dy, pv0[:, 2]])
    p_t = pv_t - T_vl[:3, 3]
    np.testing.assert_allclose(deskew_with_wheel(p_t, t, 12.0, 0.5, T_vl), p0, atol=1e-9)


def test_straight_line_motion_is_the_limit_of_a_turn():
    t = np.linspace(0, 0.1, 11)
    straight = np.column_stack(vehicle_motion_xy_yaw(t, 10.0, 0.0))
    turn = np.column_stack(vehicle_motion_xy_yaw(t, 10.0, 1e-7))
    np.testing.assert_allclose(straight, turn, atol=1e-6)


@pytest.mark.parametrize("speed_mps, yaw_rate_radps", [(10.0, 0.0), (8.0, 0.4), (5.0, -0.6)])
def test_a_scan_rolled_while_moving_gives_accurate_corners_once_deskewed(speed_mps, yaw_rate_radps):
    pts, ring, t = cast_scan(Scene([BOX]), POSE, speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps, seed=2,
                             return_time=True)
    raw = extract_corners(pts, ring, time_offset_s=t)
    fixed = extract_corners(deskew_with_wheel(pts, t, speed_mps, yaw_rate_radps), ring)
    assert len(fixed) >= 1
    assert corner_errors_m(fixed, POSE).max() < 0.02
    if len(raw):
        assert corner_errors_m(raw, POSE).max() > 0.1  # the rolled scan is off by decimetres
        assert np.all((raw.time_offset_s >= 0.0) & (raw.time_offset_s <= 0.1))


def test_integrated_odometry_matches_the_closed_form_for_a_constant_twist_and_follows_a_varying_one():
    t = np.linspace(0.0, 0.1, 50)
    odo_t = np.arange(-0.05, 0.16, 0.01)
    closed = np.column_stack(vehicle_motion_xy_yaw(t, 9.0, 0.5))
    integrated = np.column_stack(integrate_odometry_xy_yaw(t, odo_t, np.full(odo_t.size, 9.0),
                                                           np.full(odo_t.size, 0.5)))
    np.testing.assert_allclose(integrated, closed, atol=1e-6)
    # a yaw-rate pulse in the middle of the revolution: the heading at the end is its integral
    w = np.where(np.abs(odo_t - 0.05) < 0.025, 1.0, 0.0)
    _, _, yaw = integrate_odometry_xy_yaw(np.array([0.1]), odo_t, np.full(odo_t.size, 9.0), w)
    assert yaw[0] == pytest.approx(np.trapezoid(np.interp(np.linspace(0, 0.1, 10001), odo_t, w),
                                                np.linspace(0, 0.1, 10001)), abs=1e-4)
