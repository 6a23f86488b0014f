"""Oracle tests of the corner EKF and its data association (Im et al. 2016 s.3.3, s.4)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import wrap_angle_rad
from stages.evaluate import ekf
from stages.evaluate.association import associate, direction_set_difference_rad
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, EkfConfig, dead_reckon, run_ekf
from tests.stages.evaluate.ekf_settings import bare_ekf


def _straight_truth(n: int, step_m: float = 1.0) -> np.ndarray:
    return np.column_stack([np.arange(n) * step_m, np.zeros(n), np.zeros(n)])


def _observe(truth: np.ndarray, corners_en: np.ndarray, dirs_enu: np.ndarray, range_m: float = 60.0,
             sigma_m: float = 0.0, rng: np.random.Generator | None = None):
    """Exact (or noisy) vehicle-frame corner observations of every corner within range at every epoch."""
    ep, xy, dirs = [], [], []
    for k, (x, y, yaw) in enumerate(truth):
        d = corners_en - [x, y]
        c, s = np.cos(yaw), np.sin(yaw)
        v = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        vis = np.hypot(*d.T) <= range_m
        if rng is not None:
            v = v + sigma_m * rng.standard_normal(v.shape)
        ep.append(np.full(vis.sum(), k)), xy.append(v[vis]), dirs.append(wrap_angle_rad(dirs_enu[vis] - yaw))
    xy = np.concatenate(xy)
    cov = np.tile(np.eye(2) * max(sigma_m, 0.01) ** 2, (len(xy), 1, 1))
    return CornerObservations(np.concatenate(ep), xy, cov, np.concatenate(dirs))


def _map(corners_en: np.ndarray, dirs: np.ndarray, sigma_m: float = 0.01) -> CornerMap:
    return CornerMap(corners_en, np.tile(np.eye(2) * sigma_m**2, (len(corners_en), 1, 1)), dirs)


def _increments(truth: np.ndarray) -> np.ndarray:
    inc = np.zeros_like(truth)
    d = np.diff(truth[:, :2], axis=0)
    c, s = np.cos(truth[:-1, 2]), np.sin(truth[:-1, 2])
    inc[1:, 0] = c * d[:, 0] + s * d[:, 1]
    inc[1:, 1] = -s * d[:, 0] + c * d[:, 1]
    inc[1:, 2] = np.diff(truth[:, 2])
    return inc


def test_jacobian_matches_finite_differences():
    q = np.array([1.0, -2.0, 0.3])
    corners = np.array([[10.0, 5.0], [-4.0, 7.0]])
    _, H = ekf.predict_range_bearing(q, corners)
    num = np.zeros_like(H)
    for j in range(3):
        dq = np.zeros(3)
        dq[j] = 1e-6
        zp, _ = ekf.predict_range_bearing(q + dq, corners)
        zm, _ = ekf.predict_range_bearing(q - dq, corners)
        num[:, j] = ((zp - zm) / 2e-6).reshape(-1)
    np.testing.assert_allclose(H, num, atol=1e-7)


def test_straight_drive_past_two_corners_converges():
    truth = _straight_truth(40)
    corners = np.array([[15.0, 8.0], [25.0, -6.0]])
    dirs = np.array([[0.0, np.pi / 2], [np.pi, -np.pi / 2]])
    obs = _observe(truth, corners, dirs)
    q0 = truth[0] + [0.8, -0.6, np.deg2rad(2.0)]
    P0 = np.diag([1.0, 1.0, np.deg2rad(3.0) ** 2])
    paper = bare_ekf(corners={"wall_heading_sigma_deg": 0.0})  # range/bearing only, as in eqs. 3-5
    run = run_ekf(_increments(truth), obs, _map(corners, dirs), q0, P0, 0, paper)
    err = run.q - truth
    assert np.all(run.n_associated == 2)
    assert np.hypot(*err[-1, :2]) < 0.02
    assert abs(np.rad2deg(err[-1, 2])) < 0.05
    assert np.all(np.linalg.eigvalsh(run.P[-1]) < np.linalg.eigvalsh(P0).min())


# the association's gates: 60 m, chi-square 2 dof at 99 %, 15 deg between wall directions, global nearest neighbour
GATES = {"sensor_range_m": 60.0, "gate_chi2": 9.21, "angle_tol_rad": np.deg2rad(15.0), "method": "gnn"}


def test_mirrored_corner_is_rejected_by_the_angle_gate():
    q, P = np.array([0.0, 0.0, 0.0]), np.diag([1.0, 1.0, np.deg2rad(2.0) ** 2])
    map_en = np.array([[15.0, 8.0]])
    map_dirs = np.array([[0.0, np.pi / 2]])  # walls east and north of the corner
    xy = np.array([[15.0, 8.0]])
    cov = np.eye(2)[None] * 0.01
    good = associate(q, P, xy, cov, map_dirs, map_en, cov, map_dirs, **GATES)
    mirrored = associate(q, P, xy, cov, map_dirs + np.pi, map_en, cov, map_dirs, **GATES)
    swapped = associate(q, P, xy, cov, map_dirs[:, ::-1], map_en, cov, map_dirs, **GATES)  # unordered walls
    assert len(good.meas_idx) == 1 and len(swapped.meas_idx) == 1
    assert len(mirrored.meas_idx) == 0


def test_angle_gate_picks_the_right_of_two_close_corners():
    """Fig. 10 of the paper: two corners 2.5 m apart, vehicle off by more than 1 m."""
    q_true = np.array([0.0, 0.0, 0.0])
    q_est = np.array([1.5, 0.3, 0.0])  # 1.5 m ahead: corner A appears where B is
    P = np.diag([1.5**2, 1.5**2, np.deg2rad(2.0) ** 2])
    map_en = np.array([[15.0, 8.0], [16.5, 8.0]])
    map_dirs = np.array([[np.pi, -np.pi / 2], [0.0, -np.pi / 2]])  # A's walls west+south, B's east+south
    xy_a = map_en[:1] - q_true[:2]
    cov = np.eye(2)[None] * 0.01
    a = associate(q_est, P, xy_a, cov, map_dirs[:1], map_en, np.tile(cov, (2, 1, 1)), map_dirs, **GATES)
    assert a.map_idx.tolist() == [0]
    blind = associate(q_est, P, xy_a, cov, map_dirs[:1], map_en, np.tile(cov, (2, 1, 1)), map_dirs,
                      **{**GATES, "angle_tol_rad": np.pi})
    assert blind.map_idx.tolist() == [1]  # without the angle gate, position alone picks the wrong one


def test_direction_set_difference_is_order_free():
    a = np.array([[0.1, 1.6]])
    b = np.array([[1.6, 0.1], [0.1 + np.pi, 1.6]])
    d = direction_set_difference_rad(a, b)
    assert d[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert d[0, 1] == pytest.approx(np.pi - 1.5, abs=1e-9)  # best is the swapped pairing


def _one_corner_run(cfg: EkfConfig):
    truth = _straight_truth(60, 0.8)
    corner = np.array([[30.0, 9.0]])
    dirs = np.array([[0.3, 1.9]])
    obs = _observe(truth, corner, dirs)
    q0 = truth[0] + [0.7, 0.5, np.deg2rad(1.5)]
    P0 = np.diag([1.0, 1.0, np.deg2rad(2.0) ** 2])
    return truth, corner, P0, run_ekf(_increments(truth), obs, _map(corner, dirs), q0, P0, 0, cfg)


def test_one_corner_in_view_keeps_the_filter_observable():
    """Section 4.3: a single corner while moving fixes x, y and heading (with the wall-direction heading)."""
    truth, _, P0, run = _one_corner_run(bare_ekf())
    assert np.all(run.n_associated == 1)
    err = run.q - truth
    assert np.all(np.hypot(err[20:, 0], err[20:, 1]) < 0.01)
    assert np.all(np.abs(np.rad2deg(err[20:, 2])) < 0.02)
    assert np.all(np.sqrt(np.diag(run.P[-1])) < np.sqrt(np.diag(P0)) / 5)


def test_one_corner_range_bearing_only_leaves_rotation_about_the_corner():
    """With eqs. 3-5 alone, rotating the whole trajectory about the corner changes no measurement and no ICP
    increment: the residual error after convergence is exactly such a rotation (the paper's s.4.3 claim
    needs the heading from the prior or from the wall directions)."""
    truth, corner, _, run = _one_corner_run(bare_ekf(corners={"wall_heading_sigma_deg": 0.0}))
    err = run.q - truth
    delta = err[-1, 2]
    assert abs(np.rad2deg(delta)) > 0.05  # heading not recovered
    rel = truth[:, :2] - corner[0]
    predicted = np.column_stack([-delta * rel[:, 1], delta * rel[:, 0]])  # small rotation about the corner
    np.testing.assert_allclose(err[30:, :2], predicted[30:], atol=0.01)
    # the covariance stays bounded by the heading prior times the distance to the corner (~18 m x 1.3 deg)
    assert np.all(np.sqrt(np.diag(run.P[-1]))[:2] < 0.5)


def test_without_corners_the_filter_dead_reckons_and_covariance_grows():
    truth = _straight_truth(20)
    inc = _increments(truth)
    empty = CornerObservations(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2)))
    P0 = np.diag([0.01, 0.01, 1e-6])
    run = run_ekf(inc, empty, _map(np.array([[5.0, 5.0]]), np.array([[0.0, 1.0]])), truth[0], P0, 0, bare_ekf())
    np.testing.assert_allclose(run.q, dead_reckon(inc, truth[0], 0), atol=1e-12)
    assert np.all(np.diff(np.trace(run.P, axis1=1, axis2=2)) > 0)


def test_nees_is_consistent_on_noisy_measurements():
    rng = np.random.default_rng(7)
    truth = _straight_truth(200, 1.0)
    corners = np.column_stack([np.arange(5.0, 200.0, 12.0), np.tile([9.0, -7.0], 9)[:17]])
    dirs = np.column_stack([np.zeros(17), np.full(17, np.pi / 2)])
    sigma = 0.05
    obs = _observe(truth, corners, dirs, range_m=30.0, sigma_m=sigma, rng=rng)
    inc = _increments(truth)
    cfg = bare_ekf(icp={"sigma_frac": 0.02, "sigma_xy_m": 0.005, "sigma_yaw_deg": 0.05},
                   corners={"range_sigma_floor_m": 0.0, "bearing_sigma_floor_deg": 0.0})
    s_xy = cfg.icp.sigma_frac * 1.0 + cfg.icp.sigma_xy_m
    noisy = inc.copy()
    noisy[1:, :2] += s_xy * rng.standard_normal((199, 2))
    noisy[1:, 2] += cfg.icp.sigma_yaw_rad * rng.standard_normal(199)
    P0 = np.diag([0.04, 0.04, np.deg2rad(0.5) ** 2])
    q0 = truth[0] + rng.standard_normal(3) * np.sqrt(np.diag(P0))
    run = run_ekf(noisy, obs, _map(corners, dirs, 1e-4), q0, P0, 0, cfg)
    e = ekf.nees(run.q, run.P, truth)
    lo, hi = ekf.nees_band(len(e))
    assert lo * 0.8 < e.mean() < hi * 1.25
