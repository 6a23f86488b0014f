"""Oracles of a drive without GNSS: synthetic truth -> noisy ICP edges + a prior trajectory (ENU, or local with a
start pose) or a start pose alone -> the pose graph recovers the truth in the map's frame, and its stated frame
error holds the true one."""
from __future__ import annotations

import numpy as np

from stages.common.geometry import se3_from_xyz_rpy
from stages.common.records import PriorPoses
from stages.common.trajectory_metrics import horizontal_errors_m, rms
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.drive import initial_poses
from stages.posegraph.factors.graph import marginal_cov_xy_yaw, optimize
from stages.posegraph.factors.prior import information_of, prior_in_map
from tests.stages.posegraph.conftest import circuit_truth, make_drive, perturb, posegraph_config


def _yaw(T):
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def _without_gnss(T_true, rng, prior: PriorPoses):
    drive = make_drive(T_true, rng)
    drive.stamps_ns = drive.stamps_ns.astype(np.int64)
    drive.gnss_valid[:] = False
    drive.prior = prior
    drive.prior_T, drive.prior_known = prior_in_map(prior, drive.scan_ids)
    return drive


def _rows(drive_ids, stamps, T, std, frame, source):
    n = len(drive_ids)
    return PriorPoses("d0", np.asarray(drive_ids), np.asarray(stamps, np.int64), T, np.tile(std, (n, 1)),
                      np.full(n, frame, dtype=object), np.full(n, source, dtype=object), np.ones(n, bool))


def _concat(*parts):
    return PriorPoses("d0", *(np.concatenate([getattr(p, f) for p in parts]) for f in
                              ("scan_id", "stamp_ns", "T", "std", "frame", "source", "valid")))


def test_information_is_the_stated_std_in_the_body_frame():
    R = se3_from_xyz_rpy(0, 0, 0, 0, 0, np.pi / 2)[:3, :3]  # heading north: the body's x is east... turned
    info = information_of(R, np.array([0.1, 0.4, 1.0, np.nan, np.nan, 0.01]), 0.05)
    cov = np.linalg.inv(info)
    # the frame's east std (0.1 m) is the body's y axis (the vehicle points north), north (0.4 m) its -x
    assert np.allclose(np.sqrt(np.diag(cov)[3:]), [0.4, 0.1, 1.0])
    assert np.allclose(np.sqrt(np.diag(cov)[:3]), [0.05, 0.05, 0.01])


def test_enu_prior_places_the_drive_and_odometry_keeps_its_shape():
    rng = np.random.default_rng(3)
    T_true = circuit_truth()
    n = len(T_true)
    stamps = np.arange(n) * 100_000_000
    noisy = np.array([perturb(T, 0.003, 0.0, rng) for T in T_true])
    noisy[:, :2, 3] += rng.normal(0, 0.3, (n, 2))  # white 0.3 m: the prior's stated std
    drive = _without_gnss(T_true, rng, _rows(np.arange(n), stamps, noisy, [0.3, 0.3, 0.3, 0.01, 0.01, 0.01],
                                             "map_enu", "prior_file"))
    cfg = posegraph_config()
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss, cfg.prior)
    assert {p.kind for p in problem.pose_priors} == {"prior"}
    poses = optimize(problem)
    err = rms(horizontal_errors_m(poses, T_true))
    assert err < 0.6 * rms(horizontal_errors_m(noisy, T_true)) and err < 0.15, err
    # thinned: one factor per second of 0.1 s scans
    assert len(problem.pose_priors) == len(range(0, n, 10))


def test_local_prior_with_a_start_heading_is_turned_into_the_map_and_the_heading_error_is_stated():
    rng = np.random.default_rng(4)
    T_true = circuit_truth()
    n = len(T_true)
    stamps = np.arange(n) * 100_000_000
    # the prior in its own frame: the truth turned 70 deg and shifted (a SLAM trajectory starts at its identity)
    T_local_map = se3_from_xyz_rpy(5.0, -3.0, 0.0, 0.0, 0.0, np.radians(70.0))
    local = np.array([perturb(T_local_map @ T, 0.0005, 0.05, rng) for T in T_true])
    heading_err = np.radians(0.5)  # the stated start heading is 0.5 deg off, with a std of 0.5 deg
    start_T = se3_from_xyz_rpy(*T_true[0, :3, 3], 0.0, 0.0, _yaw(T_true[0]) + heading_err)
    start = _rows([0], stamps[:1], start_T[None], [0.0, 0.0, 0.0, np.nan, np.nan, np.radians(0.5)], "map_enu",
                  "start")
    prior = _concat(_rows(np.arange(n), stamps, local, [0.05, 0.05, 0.1, 0.0005, 0.0005, 0.0005], "local",
                          "prior_file"), start)
    drive = _without_gnss(T_true, rng, prior)
    init = initial_poses(drive)
    assert abs(np.degrees(np.angle(np.exp(1j * (_yaw(init[100]) - _yaw(T_true[100]))))) - 0.5) < 0.1
    cfg = posegraph_config()
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss, cfg.prior)
    assert {p.kind for p in problem.pose_priors} == {"start"}
    assert sum(b.kind == "prior" for b in problem.betweens) > 20
    poses = optimize(problem)
    # the shape is right to centimetres once the stated heading error is taken out; the frame error is that turn
    R = se3_from_xyz_rpy(*T_true[0, :3, 3], 0, 0, 0) @ se3_from_xyz_rpy(0, 0, 0, 0, 0, -heading_err) \
        @ se3_from_xyz_rpy(*(-T_true[0, :3, 3]), 0, 0, 0)
    # the shape: as good as the prior's own relative to its first pose (whose error every shape factor shares)
    prior_alone = np.linalg.inv(local[0]) @ local
    prior_err = rms(horizontal_errors_m(T_true[0] @ prior_alone, T_true))
    assert rms(horizontal_errors_m(R @ poses, T_true)) < 1.2 * prior_err + 0.02, prior_err
    far = int(np.argmax(np.linalg.norm(T_true[:, :2, 3] - T_true[0, :2, 3], axis=1)))
    true_err = np.linalg.norm(poses[far, :2, 3] - T_true[far, :2, 3])
    cov = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
    stated = np.sqrt(np.trace(cov[far, :2, :2]))
    assert 0.3 < true_err / stated < 3.0, (true_err, stated)  # 0.5 deg at ~85 m: 0.7 m, stated about the same
    assert abs(np.degrees(np.sqrt(cov[far, 2, 2])) - 0.5) < 0.1


def test_a_start_heading_alone_places_odometry_and_pins_the_first_pose():
    rng = np.random.default_rng(5)
    T_true = circuit_truth(n_laps=1)
    n = len(T_true)
    start = _rows([0], [0], T_true[:1], [0.0, 0.0, 0.0, np.nan, np.nan, np.radians(0.2)], "map_enu", "start")
    drive = _without_gnss(T_true, rng, start)
    cfg = posegraph_config()
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss, cfg.prior)
    assert [p.kind for p in problem.pose_priors] == ["start"]
    poses = optimize(problem)
    assert np.linalg.norm(poses[0, :3, 3] - T_true[0, :3, 3]) < 0.01
    # odometry alone: 0.005 m / 0.3 mrad per step over a 230 m lap, within a metre
    assert np.max(horizontal_errors_m(poses, T_true)) < 1.5
    cov = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
    assert np.all(np.isfinite(cov)) and np.sqrt(np.trace(cov[-1, :2, :2])) > np.sqrt(np.trace(cov[0, :2, :2]))
    assert n > 200
