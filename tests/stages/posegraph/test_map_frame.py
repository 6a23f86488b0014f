"""Oracles of the map frame's S-transformation (``stages/posegraph/map_frame.py``): the sparse covariance operator
equals the dense inverse of the graph's information; the frame and relative covariances equal the projection
computed densely; on Monte-Carlo drives with a Gauss-Markov GNSS bias the stated frame error and relative
covariances hold the true ones (NEES at its dof), while the absolute marginals overstate the relative error."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import wrap_angle_rad
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.graph import _key, build_graph, marginal_cov_xy_yaw, optimize
from stages.posegraph.map_frame import (
    _fit_operator,
    frame_basis,
    sparse_covariance_operator,
    split_frame,
    split_map_frame,
    travel_weights,
)
from tests.stages.posegraph.conftest import base_sections, circuit_truth, make_drive


def _solved(seed: int, side_m: float = 40.0):
    T_true = circuit_truth(n_laps=1, side_m=side_m)
    drive = make_drive(T_true, np.random.default_rng(seed), gnss_sigma_m=0.9, gnss_tau_s=60.0, reported_std_m=0.3)
    drive.stamps_ns = drive.stamps_ns.astype(np.int64)
    factors, gnss = base_sections({"gnss.bias_tau_s": 60.0, "gnss.std_inflation": 3.0})
    problem, _ = base_problem([drive], factors, gnss)
    poses = optimize(problem)
    return T_true, problem, poses


def test_the_sparse_operator_and_the_split_equal_the_dense_computation():
    _, problem, poses = _solved(3)
    n = problem.n_poses
    graph, values, _ = build_graph(problem, poses)
    op = sparse_covariance_operator(graph, values, [_key(i) for i in range(n)], poses[:, :3, :3])
    marg = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
    dense = op(np.eye(3 * n).reshape(n, 3, 3 * n)).reshape(3 * n, 3 * n)
    blocks = dense.reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    np.testing.assert_allclose(blocks, marg, rtol=1e-5, atol=1e-10)
    np.testing.assert_allclose(dense, dense.T, rtol=1e-6, atol=1e-10)
    en = poses[:, :2, 3]
    w = travel_weights(en)
    split = split_frame(op, marg, en, w)
    G = frame_basis(en, split.reference_en_m).reshape(3 * n, 3)
    Wd = np.diag(np.repeat(w, 3) * np.tile([1.0, 1.0, 0.0], n))
    A = np.linalg.solve(G.T @ Wd @ G, G.T @ Wd)
    P = np.eye(3 * n) - G @ A
    rel = (P @ dense @ P.T).reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
    np.testing.assert_allclose(split.cov_frame, A @ dense @ A.T, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(split.cov_relative, rel, rtol=1e-5, atol=1e-10)
    i, j = 5, 90
    cross = (P @ dense @ P.T)[3 * i:3 * i + 3, 3 * j:3 * j + 3]
    np.testing.assert_allclose(split.relative_cross(i, j, dense[3 * i:3 * i + 3, 3 * j:3 * j + 3],
                                                    G.reshape(n, 3, 3)), cross, rtol=1e-5, atol=1e-10)
    # the frame is the drive's common error: the relative part is far below the absolute one
    assert np.sqrt(np.mean(rel[:, 0, 0])) < 0.2 * np.sqrt(np.mean(marg[:, 0, 0]))


def test_travel_weights_do_not_count_a_stop_many_times():
    en = np.column_stack([np.r_[np.zeros(50), np.arange(1.0, 11.0)], np.zeros(60)])
    w = travel_weights(en)
    assert w.sum() == pytest.approx(1.0)
    assert w[:49].sum() == pytest.approx(0.0) and w[49] == pytest.approx(0.05)


def test_the_stated_frame_and_relative_errors_hold_the_true_ones_over_monte_carlo_drives():
    nees_frame, nees_rel, nees_abs_after_fit = [], [], []
    for seed in range(16):
        T_true, problem, poses = _solved(100 + seed)
        marg = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
        split = split_map_frame(problem, poses, np.zeros(problem.n_poses, int), marg)
        en = poses[:, :2, 3]
        yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
        e = np.column_stack([en - T_true[:, :2, 3], wrap_angle_rad(yaw(poses) - yaw(T_true))])
        G = frame_basis(en, split.reference_en_m)
        g = np.einsum("nak,na->k", _fit_operator(G, travel_weights(en)), e)
        r = e - np.einsum("nak,k->na", G, g)
        nees_frame.append(g @ np.linalg.solve(split.cov_frame, g))
        rel = split.cov_relative[:, :2, :2]
        nees_rel.append(np.mean(np.einsum("na,nab,nb->n", r[:, :2], np.linalg.inv(rel), r[:, :2])))
        nees_abs_after_fit.append(np.mean(np.einsum("na,nab,nb->n", r[:, :2], np.linalg.inv(marg[:, :2, :2]),
                                                    r[:, :2])))
    # chi-square 3 dof averaged over 16 drives: std 0.61; the relative NEES (2 dof) is a drive mean of correlated terms
    assert 1.5 < np.mean(nees_frame) < 4.8, nees_frame
    assert 1.0 < np.mean(nees_rel) < 3.5, nees_rel
    assert np.mean(nees_abs_after_fit) < 0.1  # the absolute marginal would claim ten times the error the map has
