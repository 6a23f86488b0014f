"""Horizontal survey anchors checked against each other: a match locked onto a wrong repetition of the paint is
dropped, anchors that agree (also ones fixing one direction only) are kept, a lone anchor cannot be checked."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from stages.posegraph.anchors.anchor_consensus import anchor_consensus

G1, G2 = chi2.ppf(0.99, 1), chi2.ppf(0.99, 2)
KW = dict(window_m=300.0, drift_sigma_m=0.1, gate_chi2_1=G1, gate_chi2_2=G2)


def _info(sigma_e: float, sigma_n: float | None) -> np.ndarray:
    """ENU information; ``sigma_n=None``: east fixed only (a lane line running north-south)."""
    return np.diag([sigma_e**-2, 0.0 if sigma_n is None else sigma_n**-2])


def test_aliased_anchors_are_dropped_and_the_consistent_ones_kept():
    rng = np.random.default_rng(4)
    common = np.array([0.33, -0.11])  # the pass-2 estimate's error all anchors should see
    n = 12
    shifts = common + rng.normal(0, 0.03, (n, 2))
    info = np.stack([_info(0.03, 0.03)] * n)
    info[3] = _info(0.03, None)  # one anchor fixes east only: consistent in east, kept
    shifts[3, 1] = 0.0           # (its north component is not claimed)
    bad = [5, 8, 9]
    shifts[5] += [1.0, 0.0]      # crosswalk stripe one metre over
    shifts[8] += [0.0, -3.5]     # the next lane
    shifts[9] += [-0.6, 0.5]     # a distorted submap
    res = anchor_consensus(shifts, info, np.zeros(n, int), np.arange(n) * 20.0, **KW)
    assert not res.keep[bad].any()
    assert res.keep[np.setdiff1d(np.arange(n), bad)].all()
    assert all("inconsistent" in res.reason[i] for i in bad)


def test_east_only_anchor_is_not_judged_on_north():
    shifts = np.array([[0.2, 0.0], [0.2, 0.5], [0.21, 0.5]])
    info = np.stack([_info(0.03, None), _info(0.03, 0.03), _info(0.03, 0.03)])
    res = anchor_consensus(shifts, info, np.zeros(3, int), np.array([0.0, 10.0, 20.0]), **KW)
    assert res.keep.all()


def test_lone_or_far_or_other_drive_anchor_cannot_be_checked():
    shifts = np.array([[0.3, 0.1], [0.31, 0.1], [0.3, 0.1], [0.3, 0.1]])
    info = np.stack([_info(0.03, 0.03)] * 4)
    res = anchor_consensus(shifts, info, np.array([0, 0, 1, 0]), np.array([0.0, 50.0, 60.0, 900.0]), **KW)
    assert res.keep.tolist() == [True, True, False, False]
    assert "cannot be checked" in res.reason[2] and "cannot be checked" in res.reason[3]


def test_a_slow_drift_of_the_estimate_error_is_not_an_inconsistency():
    n = 20
    travel = np.arange(n) * 15.0
    shifts = np.column_stack([0.3 + 0.0005 * travel, -0.1 + 0.0002 * travel])  # 0.15 m over 300 m
    res = anchor_consensus(shifts, np.stack([_info(0.02, 0.02)] * n), np.zeros(n, int), travel, **KW)
    assert res.keep.all()
