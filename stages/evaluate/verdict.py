"""Verdicts of an evaluation: map coverage of the drive, and each target of issue 28 met or missed (pure numpy).

Coverage: the share of epochs (with a valid GNSS/INS fix) that have a map corner within the sensor range of
the GNSS/INS position, and the share where the EKF associated at least one map corner. Below either threshold
the verdict is "no coverage": a drive that does not overlap the map must not score (a drive 60 km away once
evaluated with exit 0 and EKF 0.11 m, never having associated a corner).

Targets are judged against the map-relative reference when there is one (``truth_in_map``: the truth fitted onto
the map's corners, else ``map``: the pose graph's co-registration of the drive), else against the absolute truth
(``metrics.JUDGE_ORDER``); the verdict names the reference it used. The EKF's metrics count the epochs from its
first map-corner association on (``metrics.summarize_localized``) and its start-up time is a target of its own.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from stages.evaluate.metrics import JUDGE_ORDER

if TYPE_CHECKING:
    from stages.evaluate.params import TargetConfig



def coverage(gnss_q: np.ndarray, gnss_valid: np.ndarray, map_en_m: np.ndarray, n_associated: np.ndarray | None,
             start_epoch: int, sensor_range_m: float, min_in_range: float, min_associated: float) -> dict:
    """Coverage entry of metrics.json (shares in [0, 1]; ``ok`` False means "no coverage")."""
    from scipy.spatial import cKDTree

    ok = np.asarray(gnss_valid, bool) & np.all(np.isfinite(gnss_q), axis=1)
    ok[:start_epoch] = False
    n = int(ok.sum())
    in_range = np.zeros(len(ok), bool)
    if len(map_en_m) and n:
        d, _ = cKDTree(np.asarray(map_en_m, float)).query(gnss_q[ok, :2], distance_upper_bound=sensor_range_m)
        in_range[ok] = np.isfinite(d)
    share_in = float(in_range[ok].mean()) if n else 0.0
    share_assoc = None
    if n_associated is not None:
        share_assoc = float((np.asarray(n_associated)[ok] > 0).mean()) if n else 0.0
    good = n > 0 and share_in >= min_in_range and (share_assoc is None or share_assoc >= min_associated)
    return {"epochs": n, "map_corners": int(len(map_en_m)), "sensor_range_m": sensor_range_m,
            "share_corner_in_range": share_in, "share_associated": share_assoc,
            "min_share_in_range": min_in_range, "min_share_associated": min_associated, "ok": bool(good)}


NEES_DOF = 3  # x, y, yaw


def nees_state(mean: float | None, lo: float | None, hi: float | None) -> str | None:
    """Where the mean NEES lies against its two-sided 95 % chi-square band: ``consistent`` (inside), ``pessimistic``
    (below: the stated covariance is larger than the errors), ``optimistic`` (above: smaller); None without data."""
    if None in (mean, lo, hi):
        return None
    return "pessimistic" if mean < lo else "optimistic" if mean > hi else "consistent"


def judge_method(method: str, summary: dict, limits: dict[str, float], min_nees_share: float) -> dict:
    """Per target {target, value, ok}; for the EKF also ``nees_consistent``: its ``state`` against the two-sided 95 %
    band of the mean NEES (``nees_state``) and ``ratio`` = mean / 3 dof (1 = consistent; 0.14 = 7x pessimistic).
    ``ok`` when the mean is in the band, or above it with at least ``min_nees_share`` of the epochs under the
    chi-square 0.95 quantile (consecutive epochs are correlated, so the band of independent epochs is narrower than
    the mean's real spread; the share only speaks against optimism). A pessimistic mean is never ok."""
    out = {}
    for key, lim in limits.items():
        v = summary.get(key)
        out[key] = {"target": lim, "value": v, "ok": v is not None and v <= lim}
    if method == "ekf":
        lo, hi = summary.get("nees_band95") or [None, None]
        mean, share = summary.get("nees_mean"), summary.get("nees_share_below_q95")
        state = nees_state(mean, lo, hi)
        ok = state == "consistent" or (state == "optimistic" and share is not None and share >= min_nees_share)
        out["nees_consistent"] = {"band95": [lo, hi], "value": mean, "state": state,
                                  "ratio": None if mean is None else mean / NEES_DOF, "share_below_q95": share,
                                  "min_share_below_q95": min_nees_share, "ok": bool(ok)}
    return out


def nees_words(t: dict) -> str:
    """'pessimistic: 7.3x' / 'optimistic: 2.1x' / 'consistent' for a ``nees_consistent`` entry."""
    state, ratio = t.get("state"), t.get("ratio")
    if state in (None, "consistent") or not ratio:
        return str(state or "no data")
    return f"{state}: {1 / ratio if state == 'pessimistic' else ratio:.1f}x"


def judged_reference(metrics: dict[str, dict[str, dict]], method: str) -> str | None:
    """The first of ``JUDGE_ORDER`` that covers any epoch of the method's run (an EKF that never associated a map
    corner has no scored epoch but is judged: it misses its start-up target)."""
    by_ref = metrics.get(method, {})
    return next((r for r in JUDGE_ORDER if (by_ref.get(r) or {}).get("epochs")
                 or ((by_ref.get(r) or {}).get("all_epochs") or {}).get("epochs")), None)


def verdict(metrics: dict[str, dict[str, dict]], cov: dict, targets_cfg: TargetConfig) -> dict:
    """The verdict entry of metrics.json: status 'pass' | 'fail' | 'no coverage' | 'no reference'."""
    limits = targets_cfg.limits
    targets, missed, refs = {}, [], {}
    for m in (m for m in limits if m in metrics):
        ref = judged_reference(metrics, m)
        if ref is None:
            continue
        refs[m] = ref
        targets[m] = judge_method(m, metrics[m][ref], limits[m], targets_cfg.nees_share_below_q95)
        for key, t in targets[m].items():
            if not t["ok"]:
                state = f"{nees_words(t)}, " if key == "nees_consistent" else ""
                missed.append(f"{m} {key} {_fmt(t['value'])} ({state}target {_fmt(t.get('target', t.get('band95')))}"
                              f", against '{ref}')")
    if not cov["ok"]:
        status = "no coverage"
    elif not targets:
        status = "no reference"
    else:
        status = "fail" if missed else "pass"
    return {"status": status, "coverage": cov, "judged_against": refs, "targets": targets, "missed": missed}


def verdict_line(v: dict) -> str:
    """One line for the CLI and the error message."""
    c = v["coverage"]
    assoc = "-" if c["share_associated"] is None else f"{100 * c['share_associated']:.0f}%"
    cov = (f"{100 * c['share_corner_in_range']:.0f}% of {c['epochs']} epochs with a map corner within "
           f"{c['sensor_range_m']:g} m (min {100 * c['min_share_in_range']:.0f}%), {assoc} associated "
           f"(min {100 * c['min_share_associated']:.0f}%)")
    if v["status"] == "no coverage":
        return f"verdict: no coverage: {cov}"
    if v["status"] == "fail":
        return f"verdict: fail: {len(v['missed'])} target(s) missed: " + "; ".join(v["missed"]) + f" [coverage {cov}]"
    return f"verdict: {v['status']} [coverage {cov}]"


def _fmt(x) -> str:
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in x) + "]"
    return "-" if x is None else f"{x:.4g}"
