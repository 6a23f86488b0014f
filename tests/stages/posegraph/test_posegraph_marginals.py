"""Oracles of the pose marginals: QR elimination equals gtsam's Cholesky ``Marginals`` where both run, and
gives finite covariances where Cholesky gives up on a determined but badly conditioned graph."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy
from stages.posegraph.factors.graph import (
    AttitudePrior,
    Between,
    BiasLink,
    BiasPrior,
    PositionPrior,
    Problem,
    build_graph,
    marginal_cov_xy_yaw,
    pose_marginals,
)


def _straight_drive(n: int, icp_sigma_rad: float, icp_sigma_m: float, bridge_every: int) -> Problem:
    """A straight drive at 0.85 m per scan, heading 30 deg: ICP edges (a weak bridge every ``bridge_every``), a
    GNSS fix through a Gauss-Markov bias chain every 10 scans, INS gravity (no heading) at the same epochs: the
    layout ``bench_build --preset kitti`` gives the pose graph."""
    yaw = np.radians(30.0)
    T = np.array([se3_from_xyz_rpy(0.85 * k * np.cos(yaw), 0.85 * k * np.sin(yaw), 0.0, 0.0, 0.0, yaw)
                  for k in range(n)])
    step = se3_from_xyz_rpy(0.85, 0.0, 0.0, 0.0, 0.0, 0.0)
    icp = np.diag([icp_sigma_rad ** -2] * 3 + [icp_sigma_m ** -2] * 3)
    bridge = np.diag([0.15 ** -2] * 3 + [0.003 ** -2] * 3)
    betweens = [Between(k - 1, k, step, bridge if k % bridge_every == 0 else icp,
                        "bridge" if k % bridge_every == 0 else "odometry") for k in range(1, n)]
    fixes = list(range(0, n, 10))
    positions = [PositionPrior(k, T[k][:3, 3].copy(), np.full(3, 0.05), bias=j) for j, k in enumerate(fixes)]
    attitudes = [AttitudePrior(k, T[k][:3, :3].copy(), np.array([0.05, 0.05, 0.05]), with_yaw=False) for k in fixes]
    links = [BiasLink(j - 1, j, np.array([0.54, 0.54, 1.09]), 0.983) for j in range(1, len(fixes))]
    return Problem(n, T, betweens, positions, attitudes, [], len(fixes), links,
                   [BiasPrior(0, np.array([3.0, 3.0, 6.0]))])


def _qr(problem: Problem) -> list[np.ndarray]:
    graph, values, _ = build_graph(problem, problem.initial)
    tree = graph.linearize(values).eliminateMultifrontal(gtsam.Ordering.OrderingType.COLAMD, gtsam.EliminateQR)
    return [tree.marginalCovariance(gtsam.symbol("x", i)) for i in range(problem.n_poses)]


def test_qr_marginals_equal_cholesky_ones_on_a_well_conditioned_graph():
    problem = _straight_drive(60, icp_sigma_rad=0.002, icp_sigma_m=0.02, bridge_every=1000)
    graph, values, _ = build_graph(problem, problem.initial)
    chol = pose_marginals(graph, values, problem.n_poses)
    qr = _qr(problem)
    for a, b in zip(chol, qr):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-12)


def test_an_ill_conditioned_but_determined_graph_gets_finite_marginals():
    # ICP as firm as the real HDL-64E edges (information 8e7), a bridge every 22 scans: Cholesky gives up
    problem = _straight_drive(154, icp_sigma_rad=1.1e-4, icp_sigma_m=1.1e-4, bridge_every=22)
    graph, values, _ = build_graph(problem, problem.initial)
    with pytest.raises(RuntimeError, match="Indeterminate"):
        gtsam.Marginals(graph, values)
    cov = marginal_cov_xy_yaw(problem, problem.initial)
    assert np.all(np.isfinite(cov))
    std_e, std_n, std_yaw = np.sqrt(cov[:, 0]), np.sqrt(cov[:, 4]), np.sqrt(cov[:, 8])
    # absolute position through the bias prior (3 m), heading from the GNSS track only: finite, not tiny
    assert np.all((std_e > 0.5) & (std_e < 5.0)) and np.all((std_n > 0.5) & (std_n < 5.0))
    assert np.all((std_yaw > 1e-4) & (std_yaw < 0.1))
