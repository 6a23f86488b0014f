"""Oracles of the drive's relative factors beside the consecutive ICP edges: wheel increments bridging failed
ICP, wheel fusion beside every edge, span edges. Synthetic truth -> biased edges -> optimise -> compare."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.trajectory_metrics import horizontal_errors_m, rms
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.graph import optimize
from stages.posegraph.factors.wheel import calibrate_wheel, calibrated_wheel_increments
from tests.stages.posegraph.conftest import base_sections, make_drive, perturb


def test_wheel_increments_bridge_failed_icp_far_better_than_gnss_increments(two_lap_drive):
    """A 30-scan stretch of failed ICP (a degenerate street): bridged by wheel increments (scale 1 % short,
    gyro bias 0.1 deg/s, both calibrated against the accepted ICP edges) the relative error over that stretch
    stays within what the factors' heading std allows; bridged by GNSS increments it follows the GNSS noise.
    Truth is the oracle."""
    T_true, drive = two_lap_drive
    rng = np.random.default_rng(5)
    gap = np.arange(100, 130)
    drive.edge_ok[gap] = False
    drive.gnss_T[:, :3, 3] += rng.normal(0, 0.10, (drive.n, 3))  # white GNSS noise on top of the bias
    wheel_T = np.tile(np.eye(4), (drive.n, 1, 1))
    for k in range(1, drive.n):
        true_inc = se3_inverse(T_true[k - 1]) @ T_true[k]
        x, y = 0.99 * true_inc[0, 3], true_inc[1, 3]  # wheel scale 1 % short, planar
        yaw = np.arctan2(true_inc[1, 0], true_inc[0, 0]) - np.radians(0.1) * 0.1 + rng.normal(0, 1e-4)
        wheel_T[k] = se3_from_xyz_rpy(x, y, 0.0, 0.0, 0.0, yaw)
    drive.wheel_T, drive.wheel_ok = wheel_T, np.ones(drive.n, bool)
    cal = calibrate_wheel(drive)
    assert cal.scale == pytest.approx(1 / 0.99, abs=2e-3)
    assert cal.yaw_rate_bias_radps == pytest.approx(np.radians(0.1), abs=2e-4)
    calibrated = calibrated_wheel_increments(drive, cal)
    errors = {}
    for use_wheel in (False, True):
        drive.wheel_T, drive.wheel_ok = (calibrated, np.ones(drive.n, bool)) if use_wheel else (None, None)
        problem, _ = base_problem([drive], *base_sections())
        kinds = [b.kind for b in problem.betweens]
        assert kinds.count("wheel") == (len(gap) if use_wheel else 0)
        assert kinds.count("bridge") == (0 if use_wheel else len(gap))
        poses = optimize(problem)
        a, b = gap[0] - 1, gap[-1]
        d_est, d_true = poses[b, :2, 3] - poses[a, :2, 3], T_true[b, :2, 3] - T_true[a, :2, 3]
        errors[use_wheel] = float(np.linalg.norm(d_est - d_true))  # horizontal, map frame
    assert errors[True] < 0.12, errors  # 30 m at 0.017 deg heading std per scan: ~0.1 m allowed
    assert errors[True] < 0.5 * errors[False], errors


def test_wheel_fusion_corrects_icp_edges_biased_along_track(two_lap_drive):
    """A 40-scan street where ICP converges 2 cm short on every edge (few cross structures: the along-track
    direction is weak, and the information matrix does not know it). The calibrated wheel increment beside
    every edge pulls the stretch's length back towards truth; without it the stretch keeps the 0.8 m error."""
    T_true, drive = two_lap_drive
    rng = np.random.default_rng(8)
    stretch = np.arange(100, 140)
    drive.edge_T[stretch, 0, 3] -= 0.02
    wheel_T = np.tile(np.eye(4), (drive.n, 1, 1))
    for k in range(1, drive.n):
        true_inc = se3_inverse(T_true[k - 1]) @ T_true[k]
        yaw = np.arctan2(true_inc[1, 0], true_inc[0, 0])
        wheel_T[k] = se3_from_xyz_rpy(0.99 * true_inc[0, 3] + rng.normal(0, 0.001), true_inc[1, 3], 0.0, 0.0, 0.0, yaw)
    drive.wheel_T, drive.wheel_ok = wheel_T, np.ones(drive.n, bool)
    drive.wheel_T = calibrated_wheel_increments(drive, calibrate_wheel(drive))
    errors = {}
    for fusion in (False, True):
        problem, _ = base_problem([drive], *base_sections({"factors.wheel.fusion": fusion}))
        kinds = [b.kind for b in problem.betweens]
        assert kinds.count("wheel_fused") == (int(drive.edge_ok.sum()) if fusion else 0)
        poses = optimize(problem)
        a, b = stretch[0] - 1, stretch[-1]
        d_est, d_true = poses[b, :2, 3] - poses[a, :2, 3], T_true[b, :2, 3] - T_true[a, :2, 3]
        errors[fusion] = float(np.linalg.norm(d_est - d_true))
    assert errors[False] > 0.5, errors  # the bias survives the GNSS (0.85 m RMS) without the wheel
    # information-weighted: ICP 5 mm vs wheel 3 mm per edge leaves 27 % of the 0.8 m bias (0.21 m)
    assert errors[True] < 0.3 and errors[True] < 0.5 * errors[False], errors


def _heading_change_errors_deg(poses, T_true, lag=100):
    """Error of the heading change over ``lag`` scans (drift; the absolute heading is the GNSS's business)."""
    yaw = lambda T: np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))  # noqa: E731
    d_est, d_true = yaw(poses)[lag:] - yaw(poses)[:-lag], yaw(T_true)[lag:] - yaw(T_true)[:-lag]
    return np.rad2deg(d_est - d_true)


def test_span_edges_cut_a_per_edge_heading_bias_and_a_wrong_span_stays_local(two_lap_drive):
    """Consecutive ICP edges all turn 0.01 deg too far (a per-registration bias, 1 deg per 100 scans, which the
    information does not know); span edges over 10 scans carry one registration's error each. With them the
    heading change over 100 scans is pulled back towards truth. One span edge planted 1 m wrong along-track
    under the default Huber kernel moves its own stretch by far less than 1 m."""
    from stages.posegraph.factors.drive import SpanEdges

    T_true, drive = two_lap_drive
    rng = np.random.default_rng(5)
    bias = se3_from_xyz_rpy(0, 0, 0, 0, 0, np.deg2rad(0.01))
    drive.edge_T[1:] = drive.edge_T[1:] @ bias
    span = 10
    i = np.arange(0, drive.n - span, span)
    j = i + span
    T_ij = np.array([perturb(se3_inverse(T_true[a]) @ T_true[b], 0.0003, 0.005, rng) for a, b in zip(i, j)])
    info = np.tile(np.diag([0.0003 ** -2] * 3 + [0.005 ** -2] * 3), (len(i), 1, 1))
    drive.spans = SpanEdges(i, j, T_ij, info)
    out = {}
    for use in (False, True):
        problem, _ = base_problem([drive], *base_sections({"factors.span_edges": use}))
        assert sum(b.kind == "span" for b in problem.betweens) == (len(i) if use else 0)
        assert all(b.robust == "huber" for b in problem.betweens if b.kind == "span")
        poses = optimize(problem)
        out[use] = (rms(_heading_change_errors_deg(poses, T_true)), rms(horizontal_errors_m(poses, T_true)))
    assert out[False][0] > 0.5, out  # the bias survives the GNSS without span edges
    assert out[True][0] < 0.25 * out[False][0], out
    assert out[True][1] < out[False][1], out
    # a wrong span edge: 1 m along-track in the middle of a straight side
    k = int(np.searchsorted(i, 20))
    bad = T_ij.copy()
    bad[k, 0, 3] += 1.0
    drive.spans = SpanEdges(i, j, bad, info)
    poses = optimize(base_problem([drive], *base_sections())[0])
    a, b = i[k], j[k]
    d_est = np.linalg.norm(poses[b, :2, 3] - poses[a, :2, 3])
    d_true = np.linalg.norm(T_true[b, :2, 3] - T_true[a, :2, 3])
    assert abs(d_est - d_true) < 0.1, (d_est, d_true)


def test_registration_noise_adds_to_the_registrations_own_covariance():
    """The registration's information with the added stds: its covariance is the registration's plus the stds
    squared on yaw (rz), along (tx) and cross (ty), the rest unchanged; no added noise leaves it as it was."""
    from stages.posegraph.config import RegistrationNoise
    from stages.posegraph.factors.odometry import registration_information

    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-6 + np.diag([1e-8, 1e-8, 2e-8, 1e-5, 2e-5, 3e-5])
    info = np.linalg.inv(cov)
    assert registration_information(info, None) is info
    assert registration_information(info, RegistrationNoise(0.0, 0.0, 0.0)) is info
    out = registration_information(info, RegistrationNoise(0.006, 0.002, np.deg2rad(0.02)))
    expected = cov.copy()
    expected[[2, 3, 4], [2, 3, 4]] += [np.deg2rad(0.02) ** 2, 0.006 ** 2, 0.002 ** 2]
    np.testing.assert_allclose(np.linalg.inv(out), expected, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(out, out.T)


def test_registration_noise_makes_the_marginals_hold_edges_noisier_than_their_information(two_lap_drive):
    """ICP edges whose heading error is three times what their information states (the point-to-plane Hessian
    counts every point as independent evidence). Without the added noise the optimised headings leave the
    marginals' 95 % band far more often than 5 %; with the registration noise that restores the true std, the
    heading errors' NEES holds (pooled over drives drawn with five seeds). Truth is the oracle."""
    from stages.posegraph.factors.graph import marginal_cov_xy_yaw

    T_true, _ = two_lap_drive
    true_rad, stated_rad = 0.0009, 0.0003
    extra_deg = float(np.degrees(np.sqrt(true_rad ** 2 - stated_rad ** 2)))
    nees = {False: [], True: []}
    for seed in range(5):
        drive = make_drive(T_true, np.random.default_rng(100 + seed), edge_sigma_rad=true_rad)
        drive.stamps_ns = drive.stamps_ns.astype(np.int64)
        drive.edge_info[:] = np.diag([stated_rad ** -2] * 3 + [0.005 ** -2] * 3)
        for use in (False, True):
            yaw_deg = extra_deg if use else 0.0
            problem, _ = base_problem([drive], *base_sections({"factors.registration.yaw_deg": yaw_deg}))
            poses = optimize(problem)
            cov = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
            err = np.angle(np.exp(1j * (np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
                                        - np.arctan2(T_true[:, 1, 0], T_true[:, 0, 0]))))
            nees[use].append(err ** 2 / cov[:, 2, 2])
    share = {use: float(np.mean(np.concatenate(v) < 3.841)) for use, v in nees.items()}  # chi-square 1 dof, 95 %
    mean = {use: float(np.mean(np.concatenate(v))) for use, v in nees.items()}
    assert share[False] < 0.8 and mean[False] > 3.0, (share, mean)
    assert share[True] > 0.85 and 0.3 < mean[True] < 2.0, (share, mean)
