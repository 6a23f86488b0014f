"""The drift trigger (stages/posegraph/drift.py) on a synthetic incremental solve with known truth: a new pass tied
by loops to a held map pass; a clean map is not flagged, a map with a region shifted (an injected bias) is, in
that region."""
from __future__ import annotations

import numpy as np

from stages.posegraph.compute import increment_drift
from stages.posegraph.drift import loop_drift
from stages.posegraph.factors.graph import Between, PosePrior, PositionPrior, Problem, optimize
from stages.posegraph.solve import Solution
from tests.stages.posegraph.test_regions import _block, _exp


def incremental(shift_m: float, seed: int = 5):
    """(solution, n_new, held_T): a 240-pose map pass held, a new pass 0.3 m beside it with its own GNSS and loops
    every 4 poses onto the map; the map's poses 0..59 (one side of the block) shifted east by ``shift_m``."""
    rng = np.random.default_rng(seed)
    truth_map = np.array(_block(60, 1.0, 0.0))
    held = truth_map.copy()
    held[:, :2, 3] += rng.normal(0, 0.003, (len(held), 2))
    held[:60, 0, 3] += shift_m
    truth_new = truth_map.copy()
    truth_new[:, 1, 3] += 0.3
    n = len(truth_new)
    p = Problem(n, truth_new.copy())
    for i in range(n - 1):
        rel = np.linalg.inv(truth_new[i]) @ truth_new[i + 1] @ _exp(rng.normal(0, 0.002, 6))
        p.betweens.append(Between(i, i + 1, rel, np.diag([1e5] * 3 + [1e4] * 3)))
    for i in range(0, n, 2):
        p.positions.append(PositionPrior(i, truth_new[i, :3, 3] + rng.normal(0, 0.03, 3), np.full(3, 0.03), "none"))
    extra = list(range(0, len(held), 4))
    p.n_poses = n + len(extra)
    p.initial = np.concatenate([truth_new, held[extra]])
    tight = np.diag([1e-4 ** -2] * 3 + [1e-3 ** -2] * 3)
    for m, g in enumerate(extra):
        p.pose_priors.append(PosePrior(n + m, held[g], tight, "fixed"))
        rel = np.linalg.inv(truth_map[g]) @ truth_new[g] @ _exp(np.r_[rng.normal(0, 0.001, 3), rng.normal(0, 0.01, 3)])
        p.betweens.append(Between(n + m, g, rel, np.diag([0.002 ** -2] * 3 + [0.02 ** -2] * 3), "loop", "cauchy", 3.0))
    poses = optimize(p)
    return Solution(poses[:n], p), n, held


def test_a_clean_night_is_not_flagged():
    sol, n, held = incremental(0.0)
    doc = increment_drift(sol, n, held, max_poses=60)
    assert doc["advised"] == [] and sum(r["loops"] for r in doc["regions"]) == 60
    assert all(r["chi2"] < r["threshold"] for r in doc["regions"] if r["loops"])


def test_an_injected_bias_is_flagged_in_its_region():
    sol, n, held = incremental(0.15)
    doc = increment_drift(sol, n, held, max_poses=60)
    labels_shifted = {r["region"] for r in doc["regions"] if r["advised"]}
    assert labels_shifted, doc["regions"]
    # the flagged region is where the shift is (the first side of the block: north ~0, east 0..60 m)
    for r in doc["regions"]:
        if r["advised"]:
            assert r["center_en_m"][1] < 20, r


def test_region_rows_follow_the_held_map_partition():
    sol, n, held = incremental(0.0)
    doc = loop_drift(sol.problem, np.concatenate([sol.poses, sol.problem.initial[n:]]), n,
                     {n + m: g for m, g in enumerate(range(0, len(held), 4))}, held[:, :2, 3], max_poses=60)
    assert len(doc["regions"]) == 4 and doc["region_max_poses"] == 60


def test_each_region_is_tested_at_the_nights_level_over_the_regions_its_loops_reach():
    """Bonferroni: with m regions holding loops, a region's threshold is scale x chi2.ppf(1 - (1 - q) / m, 6 k)
    (scipy's quantile, computed here independently); regions without a loop are not tested and do not count."""
    from scipy.stats import chi2

    from stages.posegraph.drift import DRIFT_QUANTILE, DRIFT_SCALE

    sol, n, held = incremental(0.0)
    doc = increment_drift(sol, n, held, max_poses=60)
    tested = [r for r in doc["regions"] if r["loops"]]
    assert doc["regions_tested"] == len(tested) >= 2
    for r in tested:
        expected = DRIFT_SCALE * chi2.ppf(1.0 - (1.0 - DRIFT_QUANTILE) / len(tested), 6 * r["loops"])
        assert r["dof"] == 6 * r["loops"] and abs(r["threshold"] - expected) < 0.01
    one = increment_drift(sol, n, held, max_poses=10_000)  # one region: no correction
    assert one["regions_tested"] == 1
    r = one["regions"][0]
    assert abs(r["threshold"] - DRIFT_SCALE * chi2.ppf(DRIFT_QUANTILE, r["dof"])) < 0.01
