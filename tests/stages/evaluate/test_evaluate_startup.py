"""The EKF is scored from its first map-corner association on; its start-up is reported apart and judged by a
target of its own; the truth fitted onto the map judges before the pose graph's own poses of the drive."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fixtures.evaluate import synthetic_drive
from stages.evaluate.localize_ekf import CornerObservations
from stages.evaluate.metrics import JUDGE_ORDER, compute_errors, summarize, summarize_localized
from stages.evaluate.params import EvaluateParams
from stages.evaluate.run import evaluate_drive
from stages.evaluate.verdict import coverage, verdict


def test_summary_counts_the_epochs_from_the_first_association_and_reports_the_start_up_apart():
    n, k0, k_loc = 100, 2, 12  # first fix at epoch 2, first association at epoch 12, 10 Hz
    stamps = np.arange(n, dtype=np.int64) * 100_000_000
    ref = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    est = ref.copy()
    est[:k0] = np.nan
    est[k0:k_loc, 0] += 1.4  # the start-up fix 1.4 m off
    est[k_loc:, 1] += 0.05  # 5 cm once localized
    n_assoc = np.zeros(n, int)
    n_assoc[k_loc::3] = 2
    n_assoc[0] = 5  # before the first fix: no estimate, does not count
    s = summarize_localized(compute_errors(est, ref), n_assoc, stamps, k0)
    assert s["localized_from_epoch"] == k_loc
    assert s["startup_s"] == pytest.approx(1.0)
    assert s["epochs"] == n - k_loc and s["rms_2d_m"] == pytest.approx(0.05) and s["max_2d_m"] == pytest.approx(0.05)
    assert s["startup"]["epochs"] == k_loc - k0 and s["startup"]["max_2d_m"] == pytest.approx(1.4)
    expected_all = np.sqrt(((k_loc - k0) * 1.4**2 + (n - k_loc) * 0.05**2) / (n - k0))
    assert s["all_epochs"]["rms_2d_m"] == pytest.approx(expected_all)
    assert s["all_epochs"] == {k: summarize(compute_errors(est, ref))[k] for k in s["all_epochs"]}


def test_a_filter_that_never_associates_scores_nothing_and_misses_its_start_up_target():
    n = 50
    ref = np.zeros((n, 3))
    s = summarize_localized(compute_errors(ref + 0.01, ref), np.zeros(n, int), np.arange(n) * 10**8, 0)
    assert s["epochs"] == 0 and s["rms_2d_m"] is None and s["startup_s"] is None
    assert s["all_epochs"]["epochs"] == n
    metrics = {"ekf": {"truth": s}}
    cov = {"ok": True}
    v = verdict(metrics, cov, EvaluateParams().targets)
    assert not v["targets"]["ekf"]["startup_s"]["ok"] and v["status"] == "fail"


def test_truth_fitted_onto_the_map_judges_before_the_pose_graphs_poses():
    assert JUDGE_ORDER[:2] == ("truth_in_map", "map")
    good = {"rms_2d_m": 0.05, "p99_2d_m": 0.1, "max_2d_m": 0.1, "heading_rms_deg": 0.05, "epochs": 10,
            "startup_s": 1.0, "nees_mean": 3.0, "nees_band95": [2.5, 3.5], "nees_share_below_q95": 1.0}
    bad = dict(good, rms_2d_m=0.3)
    v = verdict({"ekf": {"map": bad, "truth_in_map": good, "truth": bad}}, {"ok": True},
                EvaluateParams().targets)
    assert v["judged_against"] == {"ekf": "truth_in_map"} and v["status"] == "pass"
    v = verdict({"ekf": {"map": bad, "truth": good}}, {"ok": True}, EvaluateParams().targets)
    assert v["judged_against"] == {"ekf": "map"} and v["status"] == "fail"


@pytest.fixture(scope="module")
def late_start():
    """The synthetic road with its first 3 s of corner observations removed and its GNSS/INS 1.6 m off."""
    rng = np.random.default_rng(8)
    d, cmap, fetch, truth, stamps = synthetic_drive(300, rng)
    c = d.corners
    keep = c.epoch >= 30
    d = dataclasses.replace(d, corners=CornerObservations(c.epoch[keep], c.xy_vehicle_m[keep], c.cov_vehicle_m2[keep],
                                                          c.dirs_vehicle_rad[keep]),
                            gnss_q=d.gnss_q + np.array([1.3, 0.5, 0.0]) - np.array([0.5, -0.3, 0.0]))
    refs = {"truth": (stamps, truth), "truth_in_map": (stamps, truth), "map": (stamps, truth + [0.3, 0.0, 0.0])}
    return d, cmap, fetch, refs, stamps


def test_a_late_first_association_is_the_start_up_and_the_drive_is_scored_after_it(late_start):
    d, cmap, fetch, refs, stamps = late_start
    # the corners alone: the markings localize earlier (below)
    p = EvaluateParams(methods=["ekf"], ekf={"markings": {"enabled": False}})
    ev = evaluate_drive(d, cmap, fetch, refs, p)
    assert ev.primary == "truth_in_map"
    s = ev.metrics["ekf"]["truth_in_map"]
    k_loc = s["localized_from_epoch"]
    assert k_loc == int(np.flatnonzero(ev.runs["ekf"].n_associated)[0]) and 30 <= k_loc <= 35
    assert s["startup_s"] == pytest.approx((stamps[k_loc] - stamps[0]) * 1e-9)
    # the first update (one corner) halves the 1.6 m start-up error; the next ones take it to centimetres
    assert s["startup"]["max_2d_m"] > 1.5 > 2 * s["max_2d_m"] and s["p95_2d_m"] < 0.1
    assert s["all_epochs"]["max_2d_m"] == pytest.approx(s["startup"]["max_2d_m"])
    cov = coverage(d.gnss_q, d.gnss_valid, cmap.en_m, ev.runs["ekf"].n_associated, 0, p.ekf.corners.sensor_range_m,
                   p.coverage.min_in_range, p.coverage.min_associated)
    v = verdict(ev.metrics, cov, p.targets)
    assert v["targets"]["ekf"]["startup_s"]["ok"] and v["targets"]["ekf"]["rms_2d_m"]["ok"]
    # the epoch of the first (partial) update counts: it is the scored maximum
    err = np.hypot(*(ev.runs["ekf"].q[k_loc, :2] - refs["truth_in_map"][1][k_loc, :2]))
    assert s["max_2d_m"] == pytest.approx(err)
    # with the start-up counted, as before, the 1.6 m start is the maximum
    p_all = EvaluateParams(methods=["ekf"], targets={"ekf_judge_after_startup": False},
                           ekf={"markings": {"enabled": False}})
    ev_all = evaluate_drive(d, cmap, fetch, refs, p_all)
    v_all = verdict(ev_all.metrics, cov, p_all.targets)
    assert not v_all["targets"]["ekf"]["max_2d_m"]["ok"] and "startup_s" not in v_all["targets"]["ekf"]
    assert ev_all.metrics["ekf"]["truth_in_map"]["max_2d_m"] == pytest.approx(s["all_epochs"]["max_2d_m"])
    # a target of 2 s is missed by a 3 s start-up
    p_strict = EvaluateParams(methods=["ekf"], targets={"ekf_startup_s": 2.0})
    assert not verdict(ev.metrics, cov, p_strict.targets)["targets"]["ekf"]["startup_s"]["ok"]


def test_road_markings_localize_the_ekf_before_its_first_corner(late_start):
    """The same late start with the road-marking measurement (the default): the 1.4 m first-fix error is taken out by
    the markings within the first second, before any corner is seen."""
    d, cmap, fetch, refs, stamps = late_start
    ev = evaluate_drive(d, cmap, fetch, refs, EvaluateParams(methods=["ekf"]))
    r = ev.runs["ekf"]
    err = np.hypot(*(r.q[:, :2] - refs["truth_in_map"][1][:, :2]).T)
    assert np.hypot(*(d.gnss_q[0, :2] - refs["truth_in_map"][1][0, :2])) > 1.4  # where the filter starts
    assert np.max(err[10:30]) < 0.15  # epochs 10-29: markings only, no corner yet
    assert int(np.flatnonzero(r.n_associated)[0]) >= 30


def test_features_that_are_not_deskewed_do_not_measure_the_ekf(late_start):
    """Without wheel odometry a scan's road features are not motion-compensated (up to 0.8 m late at 8 m/s): the EKF
    then runs on its corners alone, exactly as with the markings off."""
    d, cmap, fetch, refs, _ = late_start
    raw = dataclasses.replace(d, features_deskewed=False)
    on = evaluate_drive(raw, cmap, fetch, refs, EvaluateParams(methods=["ekf"]))
    off = evaluate_drive(d, cmap, fetch, refs, EvaluateParams(methods=["ekf"], ekf={"markings": {"enabled": False}}))
    np.testing.assert_array_equal(on.runs["ekf"].q, off.runs["ekf"].q)
