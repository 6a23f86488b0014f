"""Oracles: synthetic truth -> noisy edges + biased GNSS (+ loops) -> optimise -> recover within tolerance."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.trajectory_metrics import (
    horizontal_errors_m,
    revisit_pairs,
    rms,
    self_consistency_errors_m,
    summarize,
)
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.drive import dead_reckoning
from stages.posegraph.factors.gnss import select_epochs
from stages.posegraph.factors.graph import marginal_cov_xy_yaw, optimize
from stages.posegraph.loops.verify import LoopRecord
from stages.posegraph.solve import optimize_with_loops
from tests.stages.posegraph.conftest import base_sections, circuit_truth, perturb, posegraph_config


def _true_loops(T_true, rng, lap_len, every=5, sigma_m=0.02, sigma_rad=0.0005):
    info = np.diag([sigma_rad ** -2] * 3 + [sigma_m ** -2] * 3)
    out = []
    for i in range(0, len(T_true) - lap_len, every):
        j = i + lap_len
        T_ij = perturb(se3_inverse(T_true[i]) @ T_true[j], sigma_rad, sigma_m, rng)
        out.append(LoopRecord(i, j, 0.5, 0.9, 0.05, T_ij, True, "accepted", info))
    return out


def _lap_len(T_true):
    d = np.linalg.norm(T_true[:, :2, 3] - T_true[0, :2, 3], axis=1)
    return int(np.argmin(d[50:]) + 50)


def test_select_epochs_one_per_interval_and_skips_outages():
    stamps = (np.arange(50) * 0.1e9).astype(np.int64)
    valid = np.ones(50, bool)
    valid[12:27] = False
    idx = select_epochs(stamps, valid, 1.0)
    assert valid[idx].all() and idx[0] == 0 and 27 in idx  # first fix after the outage is used
    assert np.all(np.diff(stamps[idx]) >= 0.5e9) and len(idx) <= 5


def test_gnss_and_odometry_recover_truth_better_than_gnss(two_lap_drive):
    T_true, drive = two_lap_drive
    cfg = posegraph_config()
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss)
    poses = optimize(problem)
    gnss_rms = rms(horizontal_errors_m(drive.gnss_T, T_true))
    est_rms = rms(horizontal_errors_m(poses, T_true))
    assert est_rms < 0.75 * gnss_rms, (est_rms, gnss_rms)
    rel = summarize(poses, T_true, drive.stamps_ns * 1e-9)
    assert rel["relative_10m_rms_m"] < 0.03 and rel["vertical_rms_m"] < 0.6
    # dead reckoning alone keeps the local shape (oracle of chaining), but not the absolute frame
    dr = dead_reckoning(drive)
    assert summarize(dr, T_true, drive.stamps_ns * 1e-9)["relative_10m_rms_m"] < 0.03


@pytest.mark.parametrize("kernel", ["cauchy", "gnc"])
def test_loops_make_passes_agree_and_planted_false_loop_is_rejected(two_lap_drive, kernel):
    T_true, drive = two_lap_drive
    rng = np.random.default_rng(5)
    cfg = posegraph_config({"loops.kernel": kernel})  # GNC with the GNSS bias chain (built-in factors clone)
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss)
    lap = _lap_len(T_true)
    loops = _true_loops(T_true, rng, lap)
    # the planted false loop: two places 20 m apart declared the same, with a confident information
    i = 30
    j = int(np.argmin(np.abs(np.linalg.norm(T_true[:, :2, 3] - T_true[i, :2, 3], axis=1) - 20.0)
                      + 1e3 * (np.arange(len(T_true)) < lap)))
    false = LoopRecord(i, j, 0.0, 0.95, 0.05, np.eye(4), True, "planted", loops[0].information)
    poses = optimize_with_loops(problem, loops + [false], cfg.loops, cfg.solve)
    assert not false.accepted and "inconsistent" in false.reason
    assert sum(r.accepted for r in loops) >= 0.9 * len(loops)
    pairs = revisit_pairs(T_true, drive.stamps_ns * 1e-9, radius_m=2.0, min_dt_s=10.0)
    assert len(pairs) > 100
    sc = rms(self_consistency_errors_m(poses, T_true, pairs))
    assert sc < 0.05, sc


@pytest.mark.parametrize("bias_tau_s", [0.0, 60.0])
def test_marginal_covariances_positive_definite_and_grow_in_outage(two_lap_drive, bias_tau_s):
    """White GNSS: the outage's middle is much less certain. With the bias chain the absolute uncertainty is
    the bias's (shared by every fix of the last minute), so the outage adds only the odometry's drift."""
    from tests.stages.posegraph.conftest import make_drive

    T_true = circuit_truth(n_laps=1)
    drive = make_drive(T_true, np.random.default_rng(2), outage=slice(80, 180))
    drive.stamps_ns = drive.stamps_ns.astype(np.int64)
    # this synthetic INS heading is white (0.1 deg, no bias), which a heading prior fits: with a 100-epoch
    # outage on a 60 m square it is what holds the trajectory's rotation
    problem, _ = base_problem([drive], *base_sections({"gnss.bias_tau_s": bias_tau_s, "gnss.heading_prior": True}))
    assert not any(80 <= g.i < 180 for g in problem.positions)  # outages have no factor
    poses = optimize(problem)
    cov = marginal_cov_xy_yaw(problem, poses).reshape(-1, 3, 3)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert cov[130, 0, 0] > (1.2 if bias_tau_s == 0 else 1.0) * cov[20, 0, 0]
    gnss_rms = rms(horizontal_errors_m(drive.gnss_T[drive.gnss_valid], T_true[drive.gnss_valid]))
    assert rms(horizontal_errors_m(poses, T_true)) < 1.1 * gnss_rms  # a common bias cannot be averaged out


def test_gnss_fix_and_bias_chain_errors_match_their_formulas():
    """Built-in factors of the bias chain: fix z = T * lever + b + white (horizontal and vertical whitened
    separately), Gauss-Markov step b_1 - decay * b_0; checked against the formulas at random values."""
    import gtsam

    from stages.posegraph.factors.graph import (
        BiasLink,
        PositionPrior,
        Problem,
        _antenna_key,
        _bias_key,
        _key,
        build_graph,
    )

    rng = np.random.default_rng(0)
    T = se3_from_xyz_rpy(*rng.normal(0, 5, 3), *rng.normal(0, 0.2, 3))
    lever, z = np.array([0.4, -0.2, 1.5]), rng.normal(0, 3, 3)
    sig, link_sig, decay = np.array([0.3, 0.4, 0.9]), np.array([0.05, 0.06, 0.1]), 0.97
    problem = Problem(1, T[None], positions=[PositionPrior(0, z, sig, robust="none", lever_arm_m=lever, bias=0)],
                      n_biases=2, bias_links=[BiasLink(0, 1, link_sig, decay)])
    graph, values, tags = build_graph(problem)
    b0, b1 = rng.normal(0, 1, 3), rng.normal(0, 1, 3)
    v = gtsam.Values(values)
    v.update(_bias_key(0), -b0)  # the graph holds the negated bias
    v.update(_bias_key(1), -b1)
    antenna = T[:3, :3] @ lever + T[:3, 3]
    v.update(_antenna_key(0), antenna)
    want = 0.5 * np.sum(((antenna + b0 - z) / sig) ** 2) + 0.5 * np.sum(((-b1 + decay * b0) / link_sig) ** 2)
    assert graph.error(v) == pytest.approx(want, rel=1e-9)
    # the antenna is tied to the pose: moving it off T * lever costs (1 mm sigma)
    v.update(_antenna_key(0), antenna + np.array([0.01, 0, 0]))
    assert graph.error(v) > want + 40
    assert {name for name, _ in tags} == {"positions", "lever_arms", "bias_links"}
    assert _key(0) in [k for k in values.keys()]


def test_gravity_only_attitude_prior_leaves_heading_free_and_holds_roll_pitch():
    """heading_prior off: the INS enters as the up direction only; any heading costs nothing, a pitch error does."""
    import gtsam

    from stages.common.geometry import se3_from_xyz_rpy
    from stages.posegraph.factors.graph import AttitudePrior, Problem, build_graph

    T_ins = se3_from_xyz_rpy(0, 0, 0, 0.01, -0.02, 0.3)
    for with_yaw in (False, True):
        problem = Problem(1, T_ins[None], attitudes=[AttitudePrior(0, T_ins[:3, :3], np.full(3, 0.005), with_yaw)])
        graph, _, _ = build_graph(problem)

        def cost(roll, pitch, yaw):
            v = gtsam.Values()
            v.insert(gtsam.symbol("x", 0), gtsam.Pose3(se3_from_xyz_rpy(5, 1, 0, roll, pitch, yaw)))
            return graph.error(v)

        assert cost(0.01, -0.02, 0.3) < 1e-12
        rotated = cost(0.01, -0.02, 2.0)
        assert (rotated < 1e-12) if not with_yaw else rotated > 1e3
        assert cost(0.01, -0.03, 0.3 if with_yaw else 1.0) == pytest.approx(0.5 * (0.01 / 0.005) ** 2, rel=0.02)


def test_unknown_roll_pitch_is_not_a_firm_level_prior():
    """A GNSS without roll/pitch (KITTI OXTS) stores a level attitude. Flagged unknown, the graph takes pitch from
    the ICP edges and the GNSS heights (a 2 % climb: 1.15 deg); taken as a firm INS prior it bends to level."""
    from stages.common.geometry import se3_from_xyz_rpy
    from tests.stages.posegraph.conftest import make_drive

    pitch = -np.arctan(0.02)  # climbing along x (the convention's pitch is nose-down positive)
    T_true = np.array([se3_from_xyz_rpy(1.0 * k, 0.0, 0.02 * k, 0.0, pitch, 0.0) for k in range(120)])
    errors = {}
    for known in (True, False):
        drive = make_drive(T_true, np.random.default_rng(5), gnss_sigma_m=0.05, reported_std_m=0.1)
        drive.stamps_ns = drive.stamps_ns.astype(np.int64)
        level = drive.gnss_T.copy()
        for k in range(len(level)):  # the file has no roll/pitch: yaw only
            level[k][:3, :3] = se3_from_xyz_rpy(0, 0, 0, 0.0, 0.0, 0.0)[:3, :3]
        drive.gnss_T = level
        drive.gnss_roll_pitch_known = np.full(len(level), known)
        problem, _ = base_problem([drive], *base_sections({"gnss.every_s": 0.5}))
        poses = optimize(problem)
        est_pitch = np.arctan2(-poses[:, 2, 0], np.hypot(poses[:, 0, 0], poses[:, 1, 0]))
        errors[known] = float(np.degrees(np.abs(est_pitch - pitch).mean()))
    assert errors[False] < 0.1, errors  # pitch from edges and heights (the weak level prior costs ~0.05 deg)
    assert errors[True] > 0.5, errors  # the old behaviour: a 0-degree pitch treated as measured
