"""NEES consistency stated honestly: the two-sided band names a pessimistic or an optimistic filter; the report's
ellipse figure says its units and frame."""
from __future__ import annotations

import numpy as np
import pytest

from stages.evaluate.verdict import judge_method, nees_state, nees_words, verdict

BAND = [2.7, 3.3]  # the 95 % band of the mean NEES over ~600 epochs (3 dof)


def _ekf(mean: float, share: float) -> dict:
    return {"nees_mean": mean, "nees_band95": BAND, "nees_share_below_q95": share}


def test_a_seven_times_pessimistic_filter_is_named_so_and_misses_the_target():
    t = judge_method("ekf", _ekf(0.41, 1.0), {}, 0.95)["nees_consistent"]
    assert t["state"] == "pessimistic" and not t["ok"]  # every epoch under q95 says nothing against pessimism
    assert t["ratio"] == pytest.approx(0.41 / 3) and nees_words(t) == "pessimistic: 7.3x"


@pytest.mark.parametrize("mean, share, state, ok", [(3.0, 0.95, "consistent", True), (2.7, 0.5, "consistent", True),
                                                    (4.0, 0.96, "optimistic", True), (4.0, 0.90, "optimistic", False),
                                                    (2.0, 0.99, "pessimistic", False)])
def test_the_band_is_two_sided(mean, share, state, ok):
    t = judge_method("ekf", _ekf(mean, share), {}, 0.95)["nees_consistent"]
    assert (t["state"], t["ok"]) == (state, ok)
    assert nees_state(None, *BAND) is None


def test_the_verdict_line_says_pessimistic():
    v = verdict({"ekf": {"truth": {**_ekf(0.41, 1.0), "epochs": 600}}}, {"ok": True},
                __import__("stages.evaluate.params", fromlist=["EvaluateParams"]).EvaluateParams().target_config())
    [missed] = [m for m in v["missed"] if "nees" in m]
    assert "pessimistic: 7.3x" in missed and v["status"] == "fail"


def test_the_report_states_the_nees_and_labels_the_ellipse_axes(monkeypatch):
    from fixtures.evaluate import synthetic_drive
    from stages.evaluate import report
    from stages.evaluate.params import EvaluateParams
    from stages.evaluate.run import evaluate_drive

    rng = np.random.default_rng(3)
    d, cmap, fetch, truth, stamps = synthetic_drive(200, rng)
    ev = evaluate_drive(d, cmap, fetch, {"truth": (stamps, truth)}, EvaluateParams(n_particles=100).evaluation_config())
    figures = []
    monkeypatch.setattr(report, "_png", lambda fig: figures.append(fig) or "")
    import matplotlib

    matplotlib.use("Agg")
    report.figure_ellipses(ev, cmap)
    [ax] = figures[0].axes
    assert ax.get_xlabel() == "east (m, map ENU)" and ax.get_ylabel() == "north (m, map ENU)"
    doc = {"verdict": verdict({"ekf": {"truth": {**_ekf(0.41, 1.0), "epochs": 600}}},
                              {"ok": True, "share_corner_in_range": 1.0, "min_share_in_range": 0.5,
                               "share_associated": 1.0, "min_share_associated": 0.1, "sensor_range_m": 60.0},
                              EvaluateParams().target_config())}
    page = report._verdict_html(doc)
    assert "pessimistic: 7.3x" in page and "two-sided" in page
