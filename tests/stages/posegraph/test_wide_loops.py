"""Oracles of the wide loop search (stages/posegraph/loops/wide.py, uncertainty.py, pcm.py) on a synthetic
out-and-back drive: 400 m along a street, a U-turn, 400 m back 6 m to the side, keyframes 5 m apart, placed by a
start pose alone; its odometry's heading drifts (0.4 deg per keyframe plus a 0.2 deg bias), so the estimate puts the
two passes tens of metres apart. The loops are verified by an oracle (the truth's relative pose where the scans truly
overlap, a rejection elsewhere), so what is tested is the search, the consistency check and the rounds."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.posegraph.factors.graph import Between, PosePrior, Problem, optimize
from stages.posegraph.loops.candidates import find_candidates
from stages.posegraph.loops.pcm import consistent_set, max_clique
from stages.posegraph.loops.uncertainty import chain_covariance
from stages.posegraph.loops.verify import LoopRecord
from stages.posegraph.loops.wide import close_wide_loops
from stages.posegraph.solve import optimize_with_loops
from tests.stages.posegraph.conftest import posegraph_config

STEP_M, LEG_M, GAP_M = 5.0, 400.0, 6.0
SIG_T, SIG_YAW = 0.05, np.radians(0.4)


def out_and_back() -> np.ndarray:
    """Truth (N,4,4): east along y=0, a U-turn to the left, west along y=GAP_M."""
    poses = [(x, 0.0, 0.0) for x in np.arange(0.0, LEG_M + 1e-9, STEP_M)]
    for a in np.linspace(-np.pi / 2, np.pi / 2, 5)[1:-1]:
        poses.append((LEG_M + GAP_M / 2 * np.cos(a), GAP_M / 2 + GAP_M / 2 * np.sin(a), a + np.pi / 2))
    poses += [(x, GAP_M, np.pi) for x in np.arange(LEG_M, -1e-9, -STEP_M)]
    return np.array([se3_from_xyz_rpy(x, y, 0, 0, 0, yaw) for x, y, yaw in poses])


def drifting_problem(T_true: np.ndarray, seed: int = 5, bias_deg: float = 0.2):
    rng = np.random.default_rng(seed)
    n = len(T_true)
    info = np.diag([1e4, 1e4, SIG_YAW ** -2, SIG_T ** -2, SIG_T ** -2, 1e4])
    betweens, est = [], [T_true[0]]
    for k in range(1, n):
        rel = se3_inverse(T_true[k - 1]) @ T_true[k]
        noisy = rel @ se3_from_xyz_rpy(*rng.normal(0, SIG_T, 2), 0, 0, 0,
                                       rng.normal(np.radians(bias_deg), SIG_YAW))
        betweens.append(Between(k - 1, k, noisy, info, "odometry"))
        est.append(est[-1] @ noisy)
    start_info = np.diag([400.0, 400.0, np.radians(0.3) ** -2, 400.0, 400.0, 400.0])
    problem = Problem(n, np.array(est), betweens, pose_priors=[PosePrior(0, T_true[0], start_info, "start")])
    drive = SimpleNamespace(n=n, gnss_valid=np.zeros(n, bool), stamps_ns=np.arange(n, dtype=np.int64) * 500_000_000)
    return problem, drive


def oracle(T_true: np.ndarray, wrong: tuple[int, int] | None = None, overlap_m: float = 10.0):
    """A verifier: the truth's relative pose (1 cm, 0.05 deg noise) where the scans are within ``overlap_m``; the pair
    ``wrong`` (when proposed) accepted 8 m off along the street, as a repeated facade would be matched."""
    info = np.diag([1e4, 1e4, 1e4, 2500.0, 2500.0, 2500.0])
    calls = {"wrong_proposed": False}

    def verify(cands, poses):
        out = []
        for c in cands:
            T = se3_inverse(T_true[c.i]) @ T_true[c.j]
            ok = np.linalg.norm(T[:2, 3]) < overlap_m
            if wrong is not None and (c.i, c.j) == wrong:
                T = T @ se3_from_xyz_rpy(8.0, 0, 0, 0, 0, 0)
                ok = calls["wrong_proposed"] = True
            out.append(LoopRecord(c.i, c.j, c.prior_distance_m, 0.7 if ok else 0.1, 0.02, T, bool(ok),
                                  "accepted" if ok else "inlier share 0.10 < 0.50", info if ok else None))
        return out
    return verify, calls


def passes_gap_error(poses: np.ndarray, T_true: np.ndarray) -> float:
    """Largest error (m) of the return pass's position relative to the outbound pass: for each return pose, its
    truly nearest outbound pose; the estimate's offset between them against the truth's."""
    n_out = int(LEG_M / STEP_M) + 1
    out_t, back_t = T_true[:n_out, :2, 3], T_true[n_out + 3:, :2, 3]
    nearest = np.argmin(np.linalg.norm(back_t[:, None] - out_t[None], axis=2), axis=1)
    est = poses[n_out + 3:, :2, 3] - poses[nearest, :2, 3]
    return float(np.max(np.linalg.norm(est - (back_t - out_t[nearest]), axis=1)))


def run(problem, drive, T_true, cfg, verify):
    poses = optimize(problem)
    stamps = drive.stamps_ns * 1e-9
    group = np.zeros(drive.n, int)
    query = np.arange(0, drive.n, 1)
    lc = cfg.loops
    fixed = find_candidates(poses[:, :3, 3], stamps, group, query, radius_m=lc.radius_m,
                            min_separation_s=lc.min_separation_s, max_per_scan=lc.max_per_scan)
    loops = verify(fixed, poses)
    loops, poses, summary = close_wide_loops(
        problem, poses, [drive], None, lc, loops, verify_wide_fn=verify, verify_fn=verify,
        solve=lambda ls, init: optimize_with_loops(problem, ls, lc, cfg.solve, initial=init))
    poses = optimize_with_loops(problem, loops, lc, cfg.solve, initial=poses)
    return loops, poses, summary


@pytest.fixture()
def case():
    """A fresh problem per test (a solve leaves its loop factors in it)."""
    T_true = out_and_back()
    problem, drive = drifting_problem(T_true)
    return T_true, problem, drive


def test_chain_covariance_matches_monte_carlo(case):
    """The prefix-sum covariance of a relative position equals the spread of dead reckoning under the odometry's
    noise (300 draws, within 20 %)."""
    T_true, problem, drive = case
    chain = chain_covariance(problem, T_true, np.array([0, drive.n]), np.array([False]))
    a, b = 20, drive.n - 30
    predicted = chain.same_drive(a, np.array([b]))[0]
    rng = np.random.default_rng(0)
    rel = [se3_inverse(T_true[k - 1]) @ T_true[k] for k in range(1, drive.n)]
    ends = []
    for _ in range(300):
        T = T_true[a]
        for k in range(a + 1, b + 1):
            T = T @ rel[k - 1] @ se3_from_xyz_rpy(*rng.normal(0, SIG_T, 2), 0, 0, 0, rng.normal(0, SIG_YAW))
        ends.append(T[:2, 3] - T_true[a, :2, 3])
    sampled = np.cov(np.array(ends).T)
    assert np.sqrt(np.trace(predicted)) > 10.0  # the case is wide
    assert np.sqrt(np.trace(sampled)) == pytest.approx(np.sqrt(np.trace(predicted)), rel=0.2)
    assert np.linalg.eigvalsh(sampled)[-1] == pytest.approx(np.linalg.eigvalsh(predicted)[-1], rel=0.2)


def test_fixed_radius_misses_the_drifted_passes_and_the_wide_search_closes_them(case):
    T_true, problem, drive = case
    verify, _ = oracle(T_true)
    loops, poses, _ = run(problem, drive, T_true, posegraph_config({"loops.wide.enabled": False}), verify)
    before = passes_gap_error(poses, T_true)
    assert before > 20.0  # the drifted passes: tens of metres (47 m)
    problem, drive = drifting_problem(T_true)
    loops, poses, summary = run(problem, drive, T_true, posegraph_config(), verify)
    after = passes_gap_error(poses, T_true)
    assert summary["wide_accepted"] >= 2 and summary["rounds"] >= 2
    assert after < 1.0, (before, after, summary)  # 0.81 m: the U-turn's 300 m have no loop (30 s apart)


def test_a_wrong_loop_is_rejected_by_the_consistency_check(case):
    T_true, problem, drive = case
    cfg = posegraph_config()
    verify, _ = oracle(T_true)
    good, _, _ = run(problem, drive, T_true, cfg, verify)
    # a pair the wide search proposes and the oracle would reject: made to pass 8 m off
    wrong = next((r.i, r.j) for r in good if not r.accepted and r.reason.startswith("inlier"))
    verify_bad, calls = oracle(T_true, wrong=wrong)
    problem, drive = drifting_problem(T_true)
    loops, poses, _ = run(problem, drive, T_true, cfg, verify_bad)
    assert calls["wrong_proposed"]
    bad = next(r for r in loops if (r.i, r.j) == wrong)
    assert not bad.accepted and "pairwise consistency" in bad.reason, bad.reason
    assert passes_gap_error(poses, T_true) < 1.0


def test_pcm_keeps_the_consistent_loops_and_leaves_the_wrong_one():
    T_true = out_and_back()
    problem, drive = drifting_problem(T_true, bias_deg=0.0)
    pass1 = optimize(problem)
    chain = chain_covariance(problem, pass1, np.array([0, drive.n]), np.array([False]))
    n_out = int(LEG_M / STEP_M) + 1
    info = np.diag([1e4] * 3 + [2500.0] * 3)
    loops = []
    for i in (40, 42, 45, 50, 70):
        j = n_out + 3 + (n_out - 1 - i)  # the return pose beside outbound pose i
        T = se3_inverse(T_true[i]) @ T_true[j]
        loops.append(LoopRecord(i, j, 0.0, 0.7, 0.02, T, True, "accepted", info))
    wrong = replace(loops[2], T_i_j=loops[2].T_i_j @ se3_from_xyz_rpy(8.0, 0, 0, 0, 0, 0))
    travel = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pass1[:, :2, 3], axis=0), axis=1))]
    kept = consistent_set(loops[:2] + [wrong] + loops[3:], pass1, chain, 0.99, travel, 100.0, min_support=1)
    assert kept == {0, 1, 3, 4}


def test_max_clique_finds_the_largest_agreeing_set():
    ok = np.eye(6, dtype=bool)
    for a, b in ((0, 1), (0, 2), (1, 2), (2, 3), (3, 4), (3, 5), (4, 5), (2, 4), (2, 5)):
        ok[a, b] = ok[b, a] = True
    assert max_clique(ok) == [2, 3, 4, 5]


def test_drives_with_gnss_are_searched_as_before(case):
    """A drive held by GNSS (any valid fix): the wide search does nothing, the loops and poses come back as given."""
    T_true, problem, drive = case
    held = SimpleNamespace(n=drive.n, gnss_valid=np.ones(drive.n, bool), stamps_ns=drive.stamps_ns)
    verify, _ = oracle(T_true)
    poses = optimize(problem)
    loops, out, summary = close_wide_loops(problem, poses, [held], None, posegraph_config().loops, [],
                                           verify_wide_fn=verify, verify_fn=verify, solve=lambda ls, init: init)
    assert loops == [] and out is poses and summary["rounds"] == 0
