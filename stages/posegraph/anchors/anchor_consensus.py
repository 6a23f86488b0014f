"""Horizontal survey anchors checked against each other before they enter the pose graph.

Each accepted marking match claims the horizontal error of the estimate it was matched on (pass 1, before the loops)
at its keyframe: ``shift = e(t) + n`` with ``n ~ N(0, information^+)`` along the directions the markings fix. That
error ``e`` comes from the GNSS/INS and varies slowly along a drive (its bias is a slow process), so anchors near
each other in travel must agree on it. A match that locked onto a wrong repetition of the paint (a lane 3.5 m over,
a crosswalk stripe 1 m over) or onto a distorted submap is accepted alone with a narrow peak; it is caught here:
leave-one-out, each anchor is compared, in the directions it fixes, with the information-weighted mean of the other
kept anchors of its drive within ``window_m`` of travel (covariance: that mean's own plus ``drift_sigma_m``^2 per
axis for the variation of ``e`` between them), and the worst whitened residual above the chi-square gate is dropped,
again until none is left. An anchor with no neighbour that fixes its directions cannot be checked and is dropped too
(``min_neighbours``): one lone anchor cannot be told from a wrong one. Pure functions on arrays."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ConsensusResult:
    keep: np.ndarray  # (A,) bool
    whitened: np.ndarray  # (A,) chi-square of each anchor against its neighbours at its removal / the end
    reason: list[str]  # per anchor: "" when kept


def _rank_directions(info: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(2, r) unit directions an information matrix fixes."""
    vals, vecs = np.linalg.eigh(0.5 * (info + info.T))
    return vecs[:, vals > tol * max(vals.max(), 1e-300)]


def anchor_consensus(shift_en_m: np.ndarray, information_en: np.ndarray, drive: np.ndarray, travel_m: np.ndarray,
                     *, window_m: float, drift_sigma_m: float, gate_chi2_1: float, gate_chi2_2: float,
                     min_neighbours: int = 1) -> ConsensusResult:
    """Which anchors agree with their neighbours. ``shift_en_m`` (A,2), ``information_en`` (A,2,2) (rank 1 or 2),
    ``drive`` (A,) any labels, ``travel_m`` (A,) distance along the drive. Gates: chi-square quantiles for 1 and 2
    fixed directions."""
    s = np.asarray(shift_en_m, float).reshape(-1, 2)
    L = np.asarray(information_en, float).reshape(-1, 2, 2)
    drive, travel = np.asarray(drive), np.asarray(travel_m, float)
    n = len(s)
    keep = np.ones(n, bool)
    chi = np.full(n, np.nan)
    reason = [""] * n
    dirs = [_rank_directions(L[i]) for i in range(n)]

    def residual(i: int) -> tuple[float, int]:
        """(chi-square, number of neighbours) of anchor i against the kept others near it."""
        nb = np.flatnonzero(keep & (drive == drive[i]) & (np.abs(travel - travel[i]) <= window_m))
        nb = nb[nb != i]
        V = dirs[i]
        if len(nb) == 0:
            return float("nan"), 0
        info_sum = L[nb].sum(axis=0)
        # the neighbours' information along i's directions: untestable where they fix nothing
        if np.min(np.linalg.eigvalsh(V.T @ info_sum @ V)) <= 1e-9 * max(np.trace(info_sum), 1e-300):
            return float("nan"), 0
        cov_mean = np.linalg.pinv(info_sum)
        mean = cov_mean @ np.einsum("kij,kj->i", L[nb], s[nb])
        r = V.T @ (s[i] - mean)
        C = V.T @ (np.linalg.pinv(L[i]) + cov_mean + drift_sigma_m**2 * np.eye(2)) @ V
        return float(r @ np.linalg.solve(C, r)), len(nb)

    while True:
        worst, worst_excess = -1, 0.0
        for i in np.flatnonzero(keep):
            c, m = residual(i)
            chi[i] = c
            gate = gate_chi2_1 if dirs[i].shape[1] == 1 else gate_chi2_2
            if m < min_neighbours:
                excess = np.inf
                why = "no neighbouring anchor within window_m fixes its directions: cannot be checked"
            else:
                excess = c / gate
                why = f"inconsistent with the {m} neighbouring anchors: chi-square {c:.1f} > {gate:.1f}"
            if excess > 1.0 and (worst < 0 or excess > worst_excess):
                worst, worst_excess, reason_w = i, excess, why
        if worst < 0:
            return ConsensusResult(keep, chi, reason)
        keep[worst] = False
        reason[worst] = reason_w
