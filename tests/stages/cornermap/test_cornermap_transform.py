"""Lidar -> ENU: positions and angles against a hand-built pose, covariance against Monte Carlo."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.common.geometry import se3_from_xyz_rpy, transform_points
from stages.cornermap.angles import canonicalize_pairs, pair_difference_rad, wrap_rad
from stages.cornermap.transform import transform_to_enu

T_VL = se3_from_xyz_rpy(1.0, 0.2, 1.8, 0.0, 0.0, np.radians(3.0))


def test_position_and_angles_follow_the_pose():
    T_mv = se3_from_xyz_rpy(100.0, -50.0, 2.0, 0.0, 0.0, np.radians(30.0))
    xy = np.array([[10.0, 5.0]])
    theta = np.array([[0.0, np.radians(90.0)]])
    obs = transform_to_enu(xy, theta, np.zeros((1, 2, 2)), T_mv[None], T_VL[None], np.zeros((1, 3, 3)))
    expected = transform_points(T_mv @ T_VL, np.array([[10.0, 5.0, 0.0]]))[0, :2]
    np.testing.assert_allclose(obs.en_m[0], expected, atol=1e-9)
    np.testing.assert_allclose(obs.theta_enu_rad[0], wrap_rad(np.radians([33.0, 123.0])), atol=1e-9)


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(11)
    yaw = np.radians(-40.0)
    T_mv = se3_from_xyz_rpy(5.0, 7.0, 0.0, 0.0, 0.0, yaw)
    xy = np.array([25.0, -8.0])
    cov_c = np.array([[0.004, 0.001], [0.001, 0.002]])
    cov_p = np.array([[0.01, 0.002, 0.0005], [0.002, 0.02, -0.0003], [0.0005, -0.0003, 0.0004]])
    obs = transform_to_enu(xy[None], np.array([[0.0, 1.0]]), cov_c[None], T_mv[None], T_VL[None], cov_p[None])

    n = 40_000
    dp = rng.multivariate_normal(np.zeros(3), cov_p, n)
    dc = rng.multivariate_normal(np.zeros(2), cov_c, n)
    T = np.tile(T_mv, (n, 1, 1))
    T[:, 0, 3] += dp[:, 0]
    T[:, 1, 3] += dp[:, 1]
    c, s = np.cos(yaw + dp[:, 2]), np.sin(yaw + dp[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    q = np.column_stack([xy + dc, np.zeros(n), np.ones(n)])
    p = np.einsum("nij,nj->ni", T @ T_VL, q)[:, :2]
    np.testing.assert_allclose(np.cov(p.T), obs.cov_m2[0], rtol=0.05, atol=2e-5)
    np.testing.assert_allclose(p.mean(0), obs.en_m[0], atol=0.01)


@settings(max_examples=50, deadline=None)
@given(t1=st.floats(-10, 10), wedge=st.floats(0.1, 3.1), rot=st.floats(-10, 10), swap=st.booleans())
def test_canonical_order_is_rotation_invariant_and_order_free(t1, wedge, rot, swap):
    pair = np.array([[t1, t1 + wedge]])
    given_pair = pair[:, ::-1] if swap else pair
    canon = canonicalize_pairs(given_pair)
    assert 0.0 < wrap_rad(canon[0, 1] - canon[0, 0]) <= np.pi
    rotated = canonicalize_pairs(canon + rot)
    diff, swapped = pair_difference_rad(rotated, canonicalize_pairs(pair + rot))
    assert diff[0] < 1e-9 and not swapped[0]
    np.testing.assert_allclose(wrap_rad(rotated - canon - rot), 0.0, atol=1e-9)
