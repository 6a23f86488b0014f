"""Whole-drive evaluation on a synthetic road: both localizers, baselines, GNSS outage, outputs."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fixtures.evaluate import synthetic_drive
from stages.common.records import Trajectory
from stages.evaluate.outputs import epochs_table, write_report
from stages.evaluate.params import EvaluateParams
from stages.evaluate.run import evaluate_drive
from stages.evaluate.verdict import coverage, verdict


@pytest.fixture(scope="module")
def outage_evaluation():
    rng = np.random.default_rng(21)
    d, cmap, fetch, truth, stamps = synthetic_drive(600, rng, outage_s=(20.0, 30.0))
    refs = {"truth": (stamps, truth), "map": (stamps, truth + [0.02, -0.01, 0.0])}
    return evaluate_drive(d, cmap, fetch, refs, EvaluateParams(mcl={"n_particles": 500})), d, cmap


def test_gnss_outage_of_30_s_breaks_neither_localizer(outage_evaluation):
    ev, d, _ = outage_evaluation
    assert (~d.gnss_valid).sum() == 300
    for m in ("ekf", "mcl"):
        assert np.all(np.isfinite(ev.runs[m].q)), m
        s = ev.metrics[m]["truth"]
        assert s["epochs"] == 600
        assert s["max_2d_m"] < 0.5, (m, s)
    assert ev.metrics["ekf"]["truth"]["rms_2d_m"] < 0.12
    assert ev.metrics["mcl"]["truth"]["mean_abs_y_m"] < 0.1
    # the RTK/INS baseline has no estimate inside the outage; ICP dead reckoning drifts
    assert ev.metrics["rtk_ins"]["truth"]["epochs"] == 300
    assert ev.metrics["icp_dr"]["truth"]["max_2d_m"] > ev.metrics["ekf"]["truth"]["max_2d_m"]


def test_filters_start_at_the_first_valid_fix():
    rng = np.random.default_rng(4)
    d, cmap, fetch, truth, stamps = synthetic_drive(120, rng, outage_s=(0.0, 3.0))
    ev = evaluate_drive(d, cmap, fetch, {"truth": (stamps, truth)}, EvaluateParams(mcl={"n_particles": 200}))
    for m in ("ekf", "mcl", "icp_dr"):
        assert np.all(np.isnan(ev.runs[m].q[:30])) and np.all(np.isfinite(ev.runs[m].q[30:])), m


def test_outputs_metrics_tum_report_and_epochs(outage_evaluation, tmp_path):
    ev, d, cmap = outage_evaluation
    p = EvaluateParams()
    cov = coverage(d.gnss_q, d.gnss_valid, cmap.en_m, ev.runs["ekf"].n_associated, 0, p.ekf.corners.sensor_range_m,
                   p.coverage.min_in_range, p.coverage.min_associated)
    v = verdict(ev.metrics, cov, p.targets)
    doc = write_report(tmp_path, ev, cmap, None, drive="drive_1", map_info={"version": 1}, verdict=v)
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(doc))
    for m in ("ekf", "mcl", "rtk_ins", "icp_dr"):
        entry = on_disk["methods"][m]
        for key in ("rms_2d_m", "max_2d_m", "p95_2d_m", "p99_2d_m", "heading_rms_deg", "lateral_rms_m",
                    "longitudinal_rms_m", "mean_abs_x_m", "mean_abs_y_m", "mean_abs_heading_deg", "nees_mean",
                    "epochs"):
            assert key in entry and key in entry["absolute"]
        T = Trajectory.from_tum(tmp_path / f"{m}_tum.txt").T
        r = ev.runs[m]
        ok = np.all(np.isfinite(r.q), axis=1)
        np.testing.assert_allclose(T[:, 0, 3], r.q[ok, 0], atol=1e-6)
    assert on_disk["primary_reference"] == "map"
    assert on_disk["methods"]["ekf"]["targets"]["rms_2d_m"]["target"] == 0.10
    # the EKF's road-marking measurement: the share of its epochs it measured, as the run's own rows say
    rows = ev.runs["ekf"].marking_rows
    ran = np.all(np.isfinite(ev.runs["ekf"].q), axis=1)
    assert on_disk["methods"]["ekf"]["markings"] == {"share_measured": round(float(np.mean(rows[ran] > 0)), 3),
                                                     "gated_out": int(np.sum(rows < 0))}
    assert on_disk["methods"]["ekf"]["markings"]["share_measured"] > 0.5
    assert "markings" not in on_disk["methods"]["mcl"]
    assert on_disk["verdict"]["judged_against"] == {"ekf": "map", "mcl": "map"}
    assert on_disk["verdict"]["coverage"]["ok"] and on_disk["verdict"]["status"] in ("pass", "fail")
    for m, targets in on_disk["verdict"]["targets"].items():  # every verdict is the comparison it claims
        for key, t in targets.items():
            if key != "nees_consistent":
                assert t["ok"] == (t["value"] <= t["target"]) and t["value"] == on_disk["methods"][m][key]
    page = (tmp_path / "report.html").read_text()
    assert "Verdict:" in page and "rms_2d_m" in page
    assert page.count("data:image/png;base64,") >= 4
    table = epochs_table(ev, "drive_1")
    assert set(table["method"].to_pylist()) == {"ekf", "mcl", "rtk_ins", "icp_dr"}
    assert table.num_rows == 600 * 3 + 300
