"""The map's pose-error correlation kernel from the pose graph's joint marginals (posegraph/error_correlation.py)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.posegraph.error_correlation import (
    DISTANCE_BINS_M,
    fit_kernel,
    horizontal_correlation,
    pose_error_kernel,
    sample_pairs,
)
from stages.posegraph.factors.graph import _key

SIGMA0_M, SIGMA_M = 0.05, 0.01  # prior on pose 0, then each step's independent translation noise


def _random_walk_graph(n: int):
    """Poses 1 m apart along east, a prior on pose 0 and between factors with translation noise only (rotation
    held to 1e-9 rad): the horizontal positions are random walks with Cov(p_i, p_j) = (s0^2 + min(i, j) s^2) I."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    rot = [1e-9] * 3
    graph.add(gtsam.PriorFactorPose3(_key(0), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
        np.array(rot + [SIGMA0_M] * 3))))
    step = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(rot + [SIGMA_M] * 3))
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, 0, 3] = float(i)
        values.insert(_key(i), gtsam.Pose3(poses[i]))
        if i:
            graph.add(gtsam.BetweenFactorPose3(_key(i - 1), _key(i), step, noise))
    return graph, values, poses


def test_joint_marginal_correlations_equal_the_random_walks_analytic_ones():
    n = 200
    graph, values, poses = _random_walk_graph(n)
    kernel = pose_error_kernel(graph, values, poses, n, per_bin=30, seed=3)
    i, j = sample_pairs(poses[:, :2, 3], per_bin=30, seed=3)
    var = SIGMA0_M**2 + np.arange(n) * SIGMA_M**2
    rho = (SIGMA0_M**2 + np.minimum(i, j) * SIGMA_M**2) / np.sqrt(var[i] * var[j])
    d = np.abs(i - j).astype(float)
    for (lo, hi), got in zip(DISTANCE_BINS_M, kernel.bin_mean_rho):
        sel = (d >= lo) & (d < hi)
        assert got == pytest.approx(rho[sel].mean(), abs=1e-6)
    assert kernel.n_pairs == len(i) == 4 * 30
    assert 0.0 <= kernel.share < 1.0 and kernel.length_m > 0


def test_the_fit_recovers_a_squared_exponential_kernel():
    d = np.linspace(0, 150, 200)
    share, length = fit_kernel(d, 0.7 * np.exp(-0.5 * (d / 45.0) ** 2))
    assert share == pytest.approx(0.7, abs=1e-4) and length == pytest.approx(45.0, rel=1e-3)
    assert fit_kernel(np.array([1.0, 2.0]), np.array([0.5, 0.4])) == (0.0, 1.0)  # too few pairs: no correlation


def test_pairs_are_drawn_per_bin_and_repeat_with_the_seed():
    xy = np.column_stack([np.arange(500.0), np.zeros(500)])
    i, j = sample_pairs(xy, per_bin=10, seed=1)
    d = np.linalg.norm(xy[i] - xy[j], axis=1)
    for lo, hi in DISTANCE_BINS_M:
        assert np.sum((d >= lo) & (d < hi)) == 10
    assert np.all(i < j)
    i2, j2 = sample_pairs(xy, per_bin=10, seed=1)
    assert np.array_equal(i, i2) and np.array_equal(j, j2)


def test_horizontal_correlation_of_identical_and_independent_errors():
    C = np.diag([0.01, 0.04, 1.0])
    assert horizontal_correlation(C, C, C) == pytest.approx(1.0)
    assert horizontal_correlation(C, C, np.zeros((3, 3))) == 0.0


def test_a_graph_whose_cholesky_marginals_give_up_states_no_kernel_and_says_where(caplog):
    from stages.posegraph.factors.graph import build_graph
    from tests.stages.posegraph.test_posegraph_marginals import _straight_drive

    problem = _straight_drive(154, icp_sigma_rad=1.1e-4, icp_sigma_m=1.1e-4, bridge_every=22)
    graph, values, _ = build_graph(problem, problem.initial)
    with caplog.at_level("WARNING"):
        assert pose_error_kernel(graph, values, problem.initial, problem.n_poses) is None
    assert any("the map states no error correlation" in r.message and "near x" in r.message for r in caplog.records)
