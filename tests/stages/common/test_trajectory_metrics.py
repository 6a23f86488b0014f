"""Truth-vs-estimate trajectory metrics (stages/common/trajectory_metrics.py) on trajectories with known errors."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy
from stages.common.trajectory_metrics import (
    horizontal_covariance_consistency,
    relative_errors_m,
    revisit_pairs,
    rms,
    summarize,
)
from tests.stages.posegraph.conftest import circuit_truth


def test_relative_error_horizontal_part_ignores_a_height_ramp():
    """A trajectory that climbs 1 cm per metre where truth is flat: 10 cm vertical error over 10 m, none
    horizontal (to first order: the ramp also shortens the horizontal run by 0.005 %)."""
    T_true = circuit_truth(n_laps=1, z_amp_m=0.0)
    T_est = T_true.copy()
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1))])
    T_est[:, 2, 3] += 0.01 * travel
    assert rms(relative_errors_m(T_est, T_true, 10.0)) == pytest.approx(0.1, rel=0.02)
    assert rms(relative_errors_m(T_est, T_true, 10.0, horizontal=True)) < 1e-3


def test_heading_consistency_ignores_a_shared_rotation_and_sees_a_lap_turned():
    """The map turned rigidly by 0.2 deg: 0.2 deg absolute heading error, passes still agree (0). Lap 2's
    poses turned by a further 0.1 deg in place: the revisit pairs (lap 1 vs lap 2) disagree by 0.1 deg."""
    T_true = circuit_truth(n_laps=2, z_amp_m=0.0)
    stamps_s = np.arange(len(T_true)) * 1.0
    turn = se3_from_xyz_rpy(0.0, 0.0, 0.0, 0.0, 0.0, np.deg2rad(0.2))
    T_est = np.einsum("ab,nbc->nac", turn, T_true)
    s = summarize(T_est, T_true, stamps_s)
    assert s["n_revisit_pairs"] > 100
    assert s["heading_rms_deg"] == pytest.approx(0.2, abs=1e-6)
    assert s["self_consistency_heading_rms_deg"] < 1e-6
    lap2 = np.arange(len(T_true)) >= len(T_true) // 2
    T_est[lap2] = T_est[lap2] @ se3_from_xyz_rpy(0.0, 0.0, 0.0, 0.0, 0.0, np.deg2rad(0.1))
    pairs = revisit_pairs(T_true, stamps_s)
    across = np.mean(lap2[pairs[:, 0]] != lap2[pairs[:, 1]])  # the rest: a lap's end next to its own start
    assert across > 0.9
    assert summarize(T_est, T_true, stamps_s)["self_consistency_heading_rms_deg"] == pytest.approx(
        0.1 * np.sqrt(across), abs=1e-6)


def test_edge_yaw_calibration_nees_is_one_for_a_true_model_and_exposes_a_pessimistic_one():
    """Edges whose heading error is drawn from the std their information claims give NEES ~1 in every bin; a
    model claiming 10x the std gives ~0.01; bins split by the true rotation of the edge."""
    from stages.common.geometry import se3_from_xyz_rpy
    from stages.common.trajectory_metrics import edge_yaw_calibration

    rng = np.random.default_rng(5)
    n = 4000
    turn = np.where(np.arange(n) % 2 == 0, 0.001, 0.5)  # straight / turning edges (rad)
    sigma = np.where(turn > 0.1, 0.002, 0.0005)
    T_from = np.array([se3_from_xyz_rpy(i, 0, 0, 0, 0, 0.3) for i in range(n)])
    rel = np.array([se3_from_xyz_rpy(1.0, 0.1, 0, 0, 0, a) for a in turn])
    T_to = np.einsum("nab,nbc->nac", T_from, rel)
    noisy = np.einsum("nab,nbc->nac", rel, np.array([se3_from_xyz_rpy(0, 0, 0, 0, 0, e)
                                                     for e in rng.normal(0, sigma)]))
    info = np.array([np.diag([1e8, 1e8, s ** -2, 1e4, 1e4, 1e4]) for s in sigma])
    truth, i, j = np.concatenate([T_from, T_to]), np.arange(n), n + np.arange(n)
    rows = edge_yaw_calibration(noisy, info, truth, i, j, (0.0, 1.0, 45.0))
    assert [r["n"] for r in rows] == [n // 2, n // 2]
    for r, s in zip(rows, (0.0005, 0.002)):
        assert abs(r["nees"] - 1.0) < 0.1 and np.isclose(r["model_sigma_median_deg"], np.rad2deg(s))
        assert abs(r["error_rms_deg"] / np.rad2deg(s) - 1.0) < 0.06
    pessimistic = edge_yaw_calibration(noisy, info / 100.0, truth, i, j, (0.0, 1.0, 45.0))
    assert all(0.008 < r["nees"] < 0.012 for r in pessimistic)




def test_covariance_consistency_is_honest_for_drawn_errors_and_exposes_an_overconfident_one():
    from scipy.stats import chi2

    rng = np.random.default_rng(5)
    n = 20000
    angle = rng.uniform(0, np.pi, n)
    sig = np.column_stack([rng.uniform(0.005, 0.05, n), rng.uniform(0.005, 0.05, n)])
    R = np.stack([np.stack([np.cos(angle), -np.sin(angle)], -1), np.stack([np.sin(angle), np.cos(angle)], -1)], -2)
    cov = np.einsum("nij,nj,nkj->nik", R, sig**2, R)
    e = np.einsum("nij,nj->ni", R, sig * rng.standard_normal((n, 2)))
    T_true = np.tile(np.eye(4), (n, 1, 1))
    T_true[:, :2, 3] = rng.uniform(-100, 100, (n, 2))
    T_est = T_true.copy()
    T_est[:, :2, 3] += e
    honest = horizontal_covariance_consistency(T_est, T_true, cov)
    assert abs(honest["nees_mean"] - 2.0) < 0.06
    assert abs(honest["nees_share_q95"] - 0.95) < 0.005
    assert np.mean(np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[:, :, None])[:, :, 0]) <= chi2.ppf(0.95, 2)) \
        == pytest.approx(honest["nees_share_q95"])
    assert honest["true_rms_m"] == pytest.approx(honest["stated_rms_m"], rel=0.03)
    T_est[:, :2, 3] = T_true[:, :2, 3] + 3.0 * e  # the errors three times what the covariance says
    over = horizontal_covariance_consistency(T_est, T_true, cov)
    assert over["nees_mean"] == pytest.approx(18.0, rel=0.05)
    assert over["nees_share_q95"] < 0.6
