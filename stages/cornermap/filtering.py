"""Keep reliable clusters (Im et al. 2016 s.3.2: drop corners with a large covariance or a small count).

Every rejected cluster gets a reason naming the rule, the value and the threshold, several joined by "; ".
A stored covariance is always symmetric positive definite: any cluster whose map covariance is not (non-finite
or an eigenvalue <= 0) is rejected as ``non_positive_definite``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.cornermap.aggregate import ClusterSummary, largest_std_m


@dataclass(frozen=True)
class FilterThresholds:
    min_obs: int
    min_drives: int
    max_spread_m: float
    max_cov_trace_m2: float
    max_angle_spread_rad: float


def reject_reasons(summary: ClusterSummary, th: FilterThresholds) -> list[str]:
    """One string per cluster: "" when kept, else the reasons it was removed."""
    k = len(summary.n_obs)
    cov = summary.cov_map_m2
    finite = np.all(np.isfinite(cov.reshape(k, 4)), axis=1) & np.all(np.isfinite(summary.en_m), axis=1)
    safe = np.where(finite[:, None, None], cov, np.eye(2))
    min_eig = np.linalg.eigvalsh(safe)[:, 0] if k else np.empty(0)
    non_pd = ~finite | (min_eig <= 0.0)
    spread = largest_std_m(summary.cov_scatter_m2) if k else np.empty(0)
    # The gate judges the corner itself (extraction and scatter), not the pose graph's absolute uncertainty: that
    # part is a frame error shared by every corner nearby (GNSS-anchored marginals of 0.1-0.3 m), which the map
    # still stores in cov_map but which says nothing about whether this cluster is a good landmark.
    # Its extraction part is averaged over every observation, whether or not the stored one counts a drive's
    # observations as one sample (aggregate.py).
    trace = np.trace(summary.cov_extract_mean_m2, axis1=1, axis2=2) if k else np.empty(0)
    rules = [
        (non_pd, lambda i: "non_positive_definite: map covariance not SPD"),
        (summary.n_obs < th.min_obs, lambda i: f"few_observations: {summary.n_obs[i]} < {th.min_obs}"),
        (summary.n_drives < th.min_drives, lambda i: f"few_drives: {summary.n_drives[i]} < {th.min_drives}"),
        (spread > th.max_spread_m, lambda i: f"large_spread: {spread[i]:.3f} m > {th.max_spread_m:.3f} m"),
        (trace > th.max_cov_trace_m2,
         lambda i: f"large_covariance: trace (without pose part) {trace[i]:.2e} m^2 > {th.max_cov_trace_m2:.2e} m^2"),
        (summary.angle_spread_rad > th.max_angle_spread_rad,
         lambda i: f"angle_spread: {np.degrees(summary.angle_spread_rad[i]):.1f} deg > "
                   f"{np.degrees(th.max_angle_spread_rad):.1f} deg"),
    ]
    reasons: list[list[str]] = [[] for _ in range(k)]
    for mask, text in rules:
        for i in np.flatnonzero(mask):  # only the rejected clusters are visited
            reasons[i].append(text(i))
    return ["; ".join(r) for r in reasons]
