"""The 5-state EKF (gyro bias and wheel scale as states, ICP weighted by its own information) on scripted drives
with known truth: it must stay consistent where ICP fails and no corner is seen, which the ICP-only model is not."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from fixtures.evaluate import relative_increments
from stages.evaluate import ekf
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, run_ekf
from tests.stages.evaluate.ekf_settings import bare_ekf

RATE_HZ = 10.0
BIAS_RAD_S = np.deg2rad(-0.147)  # the gyro bias of the diagnosed drive
WHEEL_SCALE = 1.008


def straight(n: int, speed_mps: float = 8.0) -> np.ndarray:
    s = np.arange(n) * speed_mps / RATE_HZ
    return np.column_stack([s, np.zeros(n), np.zeros(n)])


def empty_obs() -> CornerObservations:
    return CornerObservations(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2)))


def empty_map() -> CornerMap:
    return CornerMap(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2)))


# The model the filter states, exactly (ICP's covariance is the registration's, without extra floors).
CFG = bare_ekf(icp={"sigma_frac": 0.0, "sigma_xy_m": 0.0, "sigma_yaw_deg": 0.0})


def scripted_drive(truth: np.ndarray, rng: np.random.Generator, icp_until: int, degenerate_along: bool = False,
                   bias_rad_s: float = BIAS_RAD_S, scale: float = WHEEL_SCALE):
    """Wheel/gyro increments drawn from the filter's stated model (a scale error and a gyro bias, both random
    walks, and white noise); ICP increments with a 2 mm / 0.002 deg error until ``icp_until`` and failed (NaN)
    after it, or, with ``degenerate_along``, present but 30 % short along track (a street with no structure
    across it) with the information saying so."""
    from stages.evaluate.localize_ekf import wheel_covariance

    n = len(truth)
    dt = 1.0 / RATE_HZ
    true_inc = relative_increments(truth)
    dist = np.hypot(true_inc[:, 0], true_inc[:, 1])
    bias = bias_rad_s + np.cumsum(rng.normal(0, CFG.wheel.gyro_bias_rw_rad_s_per_sqrt_s * np.sqrt(dt), n))
    sc = scale - 1.0 + np.cumsum(rng.normal(0, CFG.wheel.scale_rw_per_sqrt_m * np.sqrt(dist)))
    wheel = true_inc.copy()
    wheel[:, :2] *= (1.0 + sc)[:, None]
    for k in range(1, n):
        wheel[k] += rng.multivariate_normal(np.zeros(3), wheel_covariance(true_inc[k], CFG))
    wheel[:, 2] += bias * dt
    wheel[0] = 0.0
    icp = true_inc + rng.normal(0, 1, (n, 3)) * [0.002, 0.002, np.deg2rad(0.002)]
    cov = np.tile(np.diag([0.002**2, 0.002**2, np.deg2rad(0.002) ** 2]), (n, 1, 1))
    if degenerate_along:
        icp[icp_until:, 0] = 0.7 * true_inc[icp_until:, 0]
        cov[icp_until:, 0, 0] = 10.0**2
    else:
        icp[icp_until:] = np.nan
        cov[icp_until:] = np.nan
    stamps = (np.arange(n) * dt * 1e9).astype(np.int64)
    return wheel, icp, cov, stamps, bias, sc


def errors_and_nees(run, truth):
    e = run.q - truth
    e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return e, ekf.nees(run.q, run.P, truth)



def assert_consistent_and_band_top(nees: np.ndarray) -> float:
    """(runs, epochs) NEES of a 3-dof filter: the Monte-Carlo mean per epoch inside the two-sided 99 % band of a
    chi-square with 3 * runs dof at >= 90 % of epochs, and >= 90 % of all values under the 0.95 quantile.
    Returns the band's top."""
    runs = nees.shape[0]
    lo, hi = chi2.ppf(0.005, 3 * runs) / runs, chi2.ppf(0.995, 3 * runs) / runs
    mean = nees.mean(axis=0)
    assert np.mean((mean >= lo) & (mean <= hi)) >= 0.9, (mean.min(), mean.max(), lo, hi)
    assert np.mean(nees <= chi2.ppf(0.95, 3)) >= 0.9
    return hi

def test_straight_without_corners_and_with_a_gyro_bias_keeps_nees_consistent():
    n, runs = 600, 40  # 60 s: 10 s with ICP, then 50 s with failed ICP and no corner
    truth = straight(n)
    P0 = np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2])
    nees_5, nees_3 = [], []
    for i in range(runs):
        rng = np.random.default_rng(100 + i)
        bias = rng.normal(0, CFG.wheel.gyro_bias_sigma_rad_s)  # a draw of the prior the filter states
        scale = 1.0 + rng.normal(0, CFG.wheel.scale_sigma)
        wheel, icp, cov, stamps, _, _ = scripted_drive(truth, rng, icp_until=100, bias_rad_s=bias, scale=scale)
        q0 = truth[0] + rng.multivariate_normal(np.zeros(3), P0)
        r5 = run_ekf(icp, empty_obs(), empty_map(), q0, P0, 0, CFG, wheel_increments=wheel,
                     stamps_ns=stamps, icp_cov=cov)
        nees_5.append(errors_and_nees(r5, truth)[1][1:])
        # The paper's model with the failed ICP increments replaced by the wheel/gyro ones (the old fallback).
        fallback = np.where(np.isfinite(icp), icp, wheel)
        r3 = run_ekf(fallback, empty_obs(), empty_map(), q0, P0, 0, bare_ekf(icp={"sigma_yaw_deg": 0.004}))
        nees_3.append(errors_and_nees(r3, truth)[1][1:])
    hi = assert_consistent_and_band_top(np.array(nees_5))
    # The ICP-only model claims ICP-grade heading after the fallback: its NEES leaves the band by far.
    assert np.array(nees_3).mean(axis=0)[-1] > 10 * hi


def test_gyro_bias_is_estimated_while_icp_holds():
    n = 300
    truth = straight(n)
    rng = np.random.default_rng(7)
    wheel, icp, cov, stamps, bias_true, scale_true = scripted_drive(truth, rng, icp_until=n)
    state = ekf.EkfState(np.array([0.0, 0.0, 0.0, 0.0, 0.0]),
                         np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2, np.deg2rad(0.115) ** 2, 0.01**2]))
    cfg = CFG
    from stages.evaluate.localize_ekf import icp_covariance, wheel_covariance

    chis = []
    Q_bias = np.diag([cfg.wheel.gyro_bias_rw_rad_s_per_sqrt_s**2 * 0.1, cfg.wheel.scale_rw_per_sqrt_m**2 * 0.8])
    for k in range(1, n):
        state, chi = ekf.predict_wheel_icp(state, wheel[k], 0.1, wheel_covariance(wheel[k], cfg), icp[k],
                                           icp_covariance(icp[k], cov[k], cfg), Q_bias, cfg.icp.gate_chi2)
        chis.append(chi)
    assert np.mean(np.array(chis) > cfg.icp.gate_chi2) < 0.01  # consistent ICP passes its 99.9 % gate
    sb, ss = np.sqrt(state.P[3, 3]), np.sqrt(state.P[4, 4])
    assert abs(state.q[3] - bias_true[-1]) < 3 * sb and sb < np.deg2rad(0.03)
    assert abs(state.q[4] - scale_true[-1]) < 3 * ss and ss < 0.005


def test_degenerate_icp_direction_weighs_nothing():
    """ICP 30 % short along track in a street without cross structure, its information saying so: the filter
    follows the wheels along track and stays within its covariance."""
    n = 400
    truth = straight(n)
    rng = np.random.default_rng(3)
    wheel, icp, cov, stamps, bias_true, scale_true = scripted_drive(truth, rng, icp_until=50, degenerate_along=True)
    P0 = np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2])
    r = run_ekf(icp, empty_obs(), empty_map(), truth[0], P0, 0, CFG, wheel_increments=wheel,
                stamps_ns=stamps, icp_cov=cov)
    e, nees = errors_and_nees(r, truth)
    # ICP alone would be 0.3 * 8 m/s * 35 s = 84 m short; the wheels' scale random walk is the error left.
    assert abs(e[-1, 0]) < min(10.0, 3 * np.sqrt(r.P[-1, 0, 0]))
    assert np.mean(nees <= chi2.ppf(0.99, 3)) >= 0.95


# The ICP motion model with the gyro bias as a 4th state (``icp.gyro_bias_state``), on its own stated model.
CFG_ICP = bare_ekf(icp={"sigma_frac": 0.01, "sigma_xy_m": 0.005, "sigma_yaw_deg": 0.01, "gyro_bias_state": True})


def icp_model_drive(truth: np.ndarray, rng: np.random.Generator, icp_until: int, bias_rad_s: float):
    """ICP increments until ``icp_until``, then failed: the wheel/gyro increments replace them (``from_gyro``).
    The gyro's heading change (returned for every epoch) drifts with its bias (a random walk about
    ``bias_rad_s``) beside its white noise; every increment has the white noise of ``increment_covariance``, as the
    filter states."""
    from stages.evaluate.localize_ekf import increment_covariance

    n, dt = len(truth), 1.0 / RATE_HZ
    true_inc = relative_increments(truth)
    bias = bias_rad_s + np.cumsum(rng.normal(0, CFG_ICP.wheel.gyro_bias_rw_rad_s_per_sqrt_s * np.sqrt(dt), n))
    gyro = true_inc[:, 2] + bias * dt + rng.normal(0, CFG_ICP.wheel.gyro_sigma_yaw_rad, n)
    inc = true_inc.copy()
    for k in range(1, n):
        inc[k] += rng.multivariate_normal(np.zeros(3), increment_covariance(true_inc[k], CFG_ICP))
    from_gyro = np.arange(n) >= icp_until
    inc[from_gyro, 2] = gyro[from_gyro]
    inc[0], gyro[0] = 0.0, 0.0
    return inc, from_gyro, (np.arange(n) * dt * 1e9).astype(np.int64), gyro


def test_icp_model_with_the_gyro_bias_state_keeps_nees_consistent_on_a_straight_without_corners():
    """10 s of ICP, then 20 s of wheel/gyro fallback with a gyro bias drawn from its prior and no corner: the
    Monte-Carlo mean NEES stays in its band; the same increments without the bias state leave it tenfold. (Longer
    fallbacks take the heading error past 2 deg, where the linearised position error no longer holds.)"""
    n, runs = 300, 40
    truth = straight(n)
    P0 = np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2])
    nees_4, nees_3 = [], []
    for i in range(runs):
        rng = np.random.default_rng(500 + i)
        inc, from_gyro, stamps, _ = icp_model_drive(truth, rng, 100, rng.normal(0, CFG_ICP.wheel.gyro_bias_sigma_rad_s))
        q0 = truth[0] + rng.multivariate_normal(np.zeros(3), P0)
        r4 = run_ekf(inc, empty_obs(), empty_map(), q0, P0, 0, CFG_ICP, stamps_ns=stamps, from_gyro=from_gyro)
        nees_4.append(errors_and_nees(r4, truth)[1][1:])
        cfg3 = bare_ekf(icp={"sigma_frac": 0.01, "sigma_xy_m": 0.005, "sigma_yaw_deg": 0.01})
        r3 = run_ekf(inc, empty_obs(), empty_map(), q0, P0, 0, cfg3, stamps_ns=stamps, from_gyro=from_gyro)
        nees_3.append(errors_and_nees(r3, truth)[1][1:])
    hi = assert_consistent_and_band_top(np.array(nees_4))
    assert np.array(nees_3).mean(axis=0)[-1] > 10 * hi


def test_corners_seen_during_the_fallback_correct_the_bias_drift():
    """Sparse corners (one every ~36 m, 80 % detected) while ICP has failed and the gyro drifts 0.2 deg/s: with the
    bias state the heading error stays within 3 sigma at every epoch and its RMS is lower than without it."""
    from fixtures.evaluate import observe_corners, roadside_corners

    n = 400
    truth = straight(n)
    truth[:, 1] = 20.0
    rng = np.random.default_rng(11)
    inc, from_gyro, stamps, _ = icp_model_drive(truth, rng, 50, np.deg2rad(0.2))
    corners, dirs = roadside_corners(float(truth[-1, 0]) + 40.0, 20.0, rng, spacing_m=36.0)
    obs = CornerObservations(*observe_corners(truth, corners, dirs, rng, range_m=25.0))
    cmap = CornerMap(corners, np.tile(np.eye(2) * 1e-6, (len(corners), 1, 1)), dirs)
    P0 = np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2])
    r4 = run_ekf(inc, obs, cmap, truth[0], P0, 0, CFG_ICP, stamps_ns=stamps, from_gyro=from_gyro)
    cfg3 = bare_ekf(icp={"sigma_frac": 0.01, "sigma_xy_m": 0.005, "sigma_yaw_deg": 0.01})
    r3 = run_ekf(inc, obs, cmap, truth[0], P0, 0, cfg3, stamps_ns=stamps, from_gyro=from_gyro)
    e4, e3 = errors_and_nees(r4, truth)[0], errors_and_nees(r3, truth)[0]
    assert np.all(np.abs(e4[:, 2]) <= 3 * np.sqrt(r4.P[:, 2, 2]))
    assert np.sqrt(np.mean(e4[50:, 2] ** 2)) < np.sqrt(np.mean(e3[50:, 2] ** 2))


def test_predict_gyro_bias_matches_a_hand_computation():
    q = np.array([1.0, 2.0, 0.3, 0.002])
    L = np.array([[0.1, 0, 0, 0], [0.02, 0.2, 0, 0], [0.001, 0.002, 0.01, 0], [0, 0, 0.0005, 0.001]])
    P = L @ L.T
    Q = np.diag([0.01**2, 0.02**2, 0.001**2])
    inc, dt, qb = np.array([0.8, 0.1, 0.02]), 0.1, 1e-9
    new, Phi = ekf.predict_gyro_bias(ekf.EkfState(q, P), inc, Q, dt, True, qb)
    c, s = np.cos(0.3), np.sin(0.3)
    dyaw = 0.02 - 0.002 * dt  # the gyro's heading change less the bias over the step
    assert np.allclose(new.q, [1 + 0.8 * c - 0.1 * s, 2 + 0.8 * s + 0.1 * c, 0.3 + dyaw, 0.002])
    F = np.array([[1, 0, -0.8 * s - 0.1 * c, 0], [0, 1, 0.8 * c - 0.1 * s, 0], [0, 0, 1, -dt], [0, 0, 0, 1]])
    G = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1], [0, 0, 0]])
    assert np.allclose(Phi, F)
    assert np.allclose(new.P, F @ P @ F.T + G @ Q @ G.T + np.diag([0, 0, 0, qb]), atol=1e-15)
    # An ICP increment: the bias does not enter; the pose block is ``ekf.predict``'s.
    icp, Phi_i = ekf.predict_gyro_bias(ekf.EkfState(q, P), inc, Q, dt, False, qb)
    ref = ekf.predict(ekf.EkfState(q[:3], P[:3, :3]), inc, Q)
    assert np.allclose(icp.q[:3], ref.q) and np.allclose(icp.P[:3, :3], ref.P) and icp.P[3, 3] == P[3, 3] + qb


def test_predict_gyro_bias_transition_is_the_derivative_of_the_mean():
    """With the gyro fused into an ICP step and for a gyro step: ``Phi`` equals the finite-difference Jacobian of
    the new mean with respect to the old (the gain depends on P only)."""
    q = np.array([3.0, -1.0, 1.1, np.deg2rad(0.1)])
    P = np.diag([0.04, 0.04, np.deg2rad(0.3) ** 2, np.deg2rad(0.1) ** 2])
    Q = np.diag([0.01**2, 0.01**2, np.deg2rad(0.016) ** 2])
    inc = np.array([0.8, 0.02, np.deg2rad(1.0)])
    for from_gyro in (False, True):
        args = (inc, Q, 0.1, from_gyro, 1e-10, np.deg2rad(1.02), np.deg2rad(0.01) ** 2)
        _, Phi = ekf.predict_gyro_bias(ekf.EkfState(q, P), *args)
        num = np.zeros((4, 4))
        for j in range(4):
            h = np.zeros(4)
            h[j] = 1e-6
            up = ekf.predict_gyro_bias(ekf.EkfState(q + h, P), *args)[0].q
            dn = ekf.predict_gyro_bias(ekf.EkfState(q - h, P), *args)[0].q
            num[:, j] = (up - dn) / 2e-6
        assert np.allclose(Phi, num, atol=1e-7), (from_gyro, Phi, num)


def test_gyro_increments_flags_the_failed_and_the_gated_icp_epochs():
    from stages.evaluate.compute import fall_back_on_wheel
    from stages.evaluate.run import DriveArrays, gyro_increments

    raw = np.array([[np.nan] * 3, [0.8, 0.0, 0.0], [np.nan] * 3, [0.8, 0.0, np.deg2rad(0.2)], [0.8, 0.0, 0.0]])
    wheel = np.array([[0.0] * 3, [0.79, 0.0, 0.0], [0.8, 0.0, 0.0], [0.8, 0.0, 0.0], [0.81, 0.0, np.deg2rad(0.01)]])
    used = fall_back_on_wheel(raw, wheel, np.deg2rad(0.05))
    d = DriveArrays(np.arange(5), used, wheel, np.zeros((5, 3)), np.ones((5, 3)), np.ones(5, bool), empty_obs(),
                    np.zeros(0, np.int64), np.zeros((0, 2)), icp_raw_increments=raw)
    assert gyro_increments(d).tolist() == [True, False, True, True, False]
    assert gyro_increments(DriveArrays(*[getattr(d, f) for f in list(d.__dataclass_fields__)[:9]])) is None


def test_gyro_fused_with_icp_learns_the_bias_and_stays_consistent():
    """``icp_gyro_fusion``: the gyro's heading change measures each ICP increment's too, so 10 s of ICP estimate
    the bias; over the next 20 s of fallback without corners the Monte-Carlo mean NEES stays in its band and the
    heading error is at least three times smaller than with the bias at its prior."""
    n, runs = 300, 40
    truth = straight(n)
    P0 = np.diag([0.05**2, 0.05**2, np.deg2rad(0.05) ** 2])
    fused = CFG_ICP.replace(icp={"gyro_fusion": True})
    nees_f, yaw_f, yaw_b = [], [], []
    for i in range(runs):
        rng = np.random.default_rng(900 + i)
        bias = rng.normal(0, CFG_ICP.wheel.gyro_bias_sigma_rad_s)
        inc, from_gyro, stamps, gyro = icp_model_drive(truth, rng, 100, bias)
        q0 = truth[0] + rng.multivariate_normal(np.zeros(3), P0)
        rf = run_ekf(inc, empty_obs(), empty_map(), q0, P0, 0, fused, stamps_ns=stamps, from_gyro=from_gyro,
                     gyro_yaw_rad=gyro)
        rb = run_ekf(inc, empty_obs(), empty_map(), q0, P0, 0, CFG_ICP, stamps_ns=stamps, from_gyro=from_gyro)
        e, nees = errors_and_nees(rf, truth)
        nees_f.append(nees[1:]), yaw_f.append(e[-1, 2]), yaw_b.append(errors_and_nees(rb, truth)[0][-1, 2])
    mean_f = np.array(nees_f).mean(axis=0)
    lo, hi = chi2.ppf(0.005, 3 * runs) / runs, chi2.ppf(0.995, 3 * runs) / runs
    assert np.mean((mean_f >= lo) & (mean_f <= hi)) >= 0.9, (mean_f.min(), mean_f.max(), lo, hi)
    assert np.sqrt(np.mean(np.square(yaw_f))) < np.sqrt(np.mean(np.square(yaw_b))) / 3


def test_icp_gated_against_the_bias_corrected_gyro():
    """``icp.gyro_gate``: with the bias known to be 0.3 deg/s (0.03 deg per scan), a true ICP increment
    that a fixed 0.05 deg gate around the raw gyro would keep is kept; one 0.1 deg off is replaced by the
    wheel/gyro increment (the motion then carries the bias)."""
    from stages.evaluate.localize_ekf import _motion

    cfg = CFG_ICP.replace(icp={"gyro_fusion": True, "gyro_gate": True})  # chi-square 1 dof at 0.999
    b, dt = np.deg2rad(0.3), 0.1
    state = ekf.EkfState(np.array([0.0, 0.0, 0.0, b]), np.diag([0.01, 0.01, 1e-6, np.deg2rad(0.001) ** 2]))
    true_inc = np.array([0.8, 0.0, np.deg2rad(0.2)])
    gyro = np.array([0.0, true_inc[2] + b * dt])
    wheel = np.array([[0.0, 0.0, 0.0], [0.81, 0.0, gyro[1]]])
    stamps = np.array([0.0, dt])
    for icp_err_deg, used_icp in ((0.0, True), (0.1, False)):
        inc = np.array([[0.0, 0.0, 0.0], true_inc + [0.0, 0.0, np.deg2rad(icp_err_deg)]])
        new, used, _ = _motion(state, 1, inc, None, stamps, None, cfg, np.array([False, False]), gyro, wheel)
        assert used == used_icp
        assert abs(new.q[2] - true_inc[2]) < np.deg2rad(0.01)  # either way the heading change is the true one
        assert np.isclose(new.q[0], 0.8 if used_icp else 0.81, atol=1e-3)
