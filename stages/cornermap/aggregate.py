"""Per-cluster statistics of corner observations (pure numpy, vectorised with bincount).

Position: the information-weighted mean, x = (sum W_i)^-1 sum W_i x_i with W_i = Sigma_i^-1 (extraction + pose).
Directions: each observation's pair is first aligned to its cluster's first observation (swapped if that matches
better), then each wall direction gets a circular mean; the mean pair is re-canonicalised (angles.py).

Covariances (all 2x2, east/north, m^2):
- ``cov_scatter``: the sample covariance of the observations about the mean (the spread of one observation; the
  filter judges data quality on it, as the paper's "position error covariance of the corner").
- ``cov_map`` (what the map stores, the uncertainty of the map point that the localizer needs):
  ``mean_i(Sigma_pose_i) / n_drives + max(Sigma_extract_info, cov_scatter / n_ind)``, where the pose part
  does not average down within one drive (its error is correlated along the drive) but does across independent
  drives, and the extraction part is the larger (by trace) of the model, (sum_i Sigma_extract_i^-1)^-1, and the
  empirical standard error of the mean over ``n_ind`` independent samples. With ``scatter_per_drive`` (the
  stage's default) ``n_ind`` is the number of drives: one pass's observations of a corner share their extraction
  error (the same walls, seen from viewpoints a few metres apart), so their scatter does not average down within
  the pass; without it ``n_ind`` is the number of observations. It is symmetric positive definite by construction.
- ``cov_extract_mean``: the extraction part with ``n_ind`` = the number of observations, what the quality filter
  judges (``filtering.py``), whichever the stored covariance counts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.cornermap.angles import canonicalize_pairs, circular_mean_by_label, pair_difference_rad
from stages.cornermap.transform import EnuObservations

_COV_FLOOR_M2 = 1e-8  # regularises singular input covariances (0.1 mm std)


@dataclass(frozen=True)
class ClusterSummary:
    """K clusters."""

    en_m: np.ndarray  # (K,2)
    theta_rad: np.ndarray  # (K,2) canonical
    cov_map_m2: np.ndarray  # (K,2,2) uncertainty of the map point
    cov_scatter_m2: np.ndarray  # (K,2,2) spread of the observations
    angle_spread_rad: np.ndarray  # (K,) circular std, the larger of the two walls
    n_obs: np.ndarray  # (K,) int64
    n_drives: np.ndarray  # (K,) int32
    drives: list[str]  # comma-separated drive names
    first_seen_ns: np.ndarray
    last_seen_ns: np.ndarray
    interior_angle_rad: np.ndarray
    convex: np.ndarray  # majority vote
    cov_extract_mean_m2: np.ndarray  # (K,2,2) extraction part averaged over every observation (the filter's)
    cov_pose_m2: np.ndarray | None = None  # (K,2,2) the pose-graph part of cov_map (frame uncertainty)


def _sum2x2(labels: np.ndarray, m: np.ndarray, k: int) -> np.ndarray:
    out = np.empty((k, 2, 2))
    for a in (0, 1):
        for b in (0, 1):
            out[:, a, b] = np.bincount(labels, m[:, a, b], minlength=k)
    return out


def _sum2(labels: np.ndarray, v: np.ndarray, k: int) -> np.ndarray:
    return np.stack([np.bincount(labels, v[:, a], minlength=k) for a in (0, 1)], 1)


def _inv_spd(m: np.ndarray) -> np.ndarray:
    return np.linalg.inv(m + _COV_FLOOR_M2 * np.eye(2))


def lag_one_correlation(labels: np.ndarray, drive_code: np.ndarray, stamp_ns: np.ndarray, en_m: np.ndarray,
                        min_obs: int = 4) -> tuple[float, int]:
    """(rho, pairs): the lag-1 autocorrelation of the observations' deviations from their pass mean (one pass: one
    cluster seen by one drive), consecutive in time, pooled over every pass of at least ``min_obs`` observations:
    ``sum d_k . d_k+1 / sum d_k . d_k`` (2-D), each pass's deviations divided by their RMS. 0 with no such pass."""
    if not len(labels):
        return 0.0, 0
    key = labels.astype(np.int64) * (int(drive_code.max()) + 1 if len(drive_code) else 1) + drive_code
    _, g = np.unique(key, return_inverse=True)
    n_g = np.bincount(g)
    mean = _sum2(g, en_m, len(n_g)) / n_g[:, None]
    d = en_m - mean[g]
    # each pass's deviations in units of its own spread: a wide cluster (rejected later) does not outweigh the rest
    spread = np.sqrt(np.bincount(g, np.sum(d**2, axis=1), minlength=len(n_g)) / n_g)
    d = d / np.where(spread > 0, spread, 1.0)[g, None]
    use = n_g[g] >= min_obs
    order = np.lexsort((stamp_ns, g))
    order = order[use[order]]
    if len(order) < 2:
        return 0.0, 0
    same = g[order[1:]] == g[order[:-1]]
    num = float(np.sum(np.einsum("ni,ni->n", d[order[1:]], d[order[:-1]])[same]))
    den = float(np.sum(d[order] ** 2))
    if den <= 0 or not same.any():
        return 0.0, int(same.sum())
    # deviations from the pass's own mean bias the estimate low by about (1 + 3 rho) / n (Kendall): undone with the
    # passes' mean 1 / n over the pairs
    inv_n = float(np.mean(1.0 / n_g[g[order[1:]][same]]))
    r = num / den
    return float(min((r + inv_n) / max(1.0 - 3.0 * inv_n, 1e-3), 0.99)), int(same.sum())


def effective_samples(n_obs: np.ndarray, rho: float) -> np.ndarray:
    """Independent samples among ``n_obs`` observations of an AR(1) sequence with lag-1 correlation ``rho``: the
    variance of their mean is the single variance over ``n (1 - rho) / (1 + rho)`` (large n), between 1 and n."""
    r = float(np.clip(rho, 0.0, 0.99))
    return np.clip(np.asarray(n_obs, float) * (1.0 - r) / (1.0 + r), 1.0, np.maximum(n_obs, 1))


def shared_pose_part(labels: np.ndarray, drive_code: np.ndarray, obs: EnuObservations, W: np.ndarray,
                     W_sum: np.ndarray, k: int) -> np.ndarray:
    """(K,2,2) the pose-graph part of each cluster mean's covariance when one pass's poses share their error (one
    pass: one cluster seen by one drive; passes of different drives independent). The mean is
    ``W_sum^-1 sum_i W_i x_i``; a pose error ``d`` (east, north, yaw) common to a pass moves it by
    ``W_sum^-1 (sum_i W_i J_i) d``, whose covariance is ``A Sigma A^T`` with ``A = W_sum^-1 sum_pass W_i J_i`` and
    ``Sigma`` the pass's mean pose covariance. A yaw error thus acts through the lever arm from the weighted mean of
    the observing poses to the corner, not through each observation's own lever arm (averaging ``J_i Sigma J_i^T``
    counts the lever arm of a corner seen from 40 m ahead and 40 m behind twice, where the two cancel)."""
    key = labels.astype(np.int64) * (int(drive_code.max()) + 1 if len(drive_code) else 1) + drive_code
    pass_keys, g = np.unique(key, return_inverse=True)
    p = len(pass_keys)
    cluster_of_pass = np.zeros(p, np.int64)
    cluster_of_pass[g] = labels
    WJ = np.einsum("nij,njk->nik", W, obs.J_pose)  # (N,2,3)
    sum_WJ = np.stack([np.stack([np.bincount(g, WJ[:, a, b], minlength=p) for b in range(3)], -1)
                       for a in range(2)], -2)  # (P,2,3)
    n_pass = np.bincount(g, minlength=p)
    sig = np.stack([np.stack([np.bincount(g, obs.cov_pose_xy_yaw[:, a, b], minlength=p) for b in range(3)], -1)
                    for a in range(3)], -2) / n_pass[:, None, None]
    A = np.linalg.solve(W_sum[cluster_of_pass], sum_WJ)  # (P,2,3)
    per_pass = np.einsum("pij,pjk,plk->pil", A, sig, A)
    return _sum2x2(cluster_of_pass, per_pass, k)


def pass_mean_factor(n_obs: np.ndarray, n_eff: np.ndarray, n_drives: np.ndarray,
                     shared_fraction: float = 0.0) -> np.ndarray:
    """(K,) the variance of a cluster's mean over its scatter (the views' sample covariance about the mean) when each
    pass's view errors are a constant part ``c`` shared by the pass plus an AR(1) part ``a`` (``n_eff`` effective
    samples summed over the passes), ``var(c) = shared_fraction var(a)``, passes independent.

    Correlated views scatter less about their mean than their own spread: ``E[scatter] = var(a) (n - n / n_eff) /
    (n - 1)`` (the constant part does not scatter at all), so ``var(a) = scatter (n - 1) n_eff / (n (n_eff - 1))``
    and the AR(1) part of the mean's variance, ``var(a) / n_eff``, is ``scatter (n - 1) / (n (n_eff - 1))``, never
    above one sample per drive (``scatter / n_drives``, which ``rho`` -> 1 gives). The shared part adds
    ``shared_fraction var(a) / n_drives``: it does not average down within a pass, only across drives."""
    n = np.asarray(n_obs, float)
    n_eff = np.asarray(n_eff, float)
    d = np.maximum(np.asarray(n_drives, float), 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ar1 = np.where(n_eff > 1.0, (n - 1.0) / (n * (n_eff - 1.0)), np.inf)
        var_a = np.where(n_eff > 1.0, (n - 1.0) * n_eff / (n * (n_eff - 1.0)), 1.0)
    return np.minimum(ar1, 1.0 / d) + float(shared_fraction) * var_a / d


def aggregate_clusters(labels: np.ndarray, obs: EnuObservations, drive_code: np.ndarray, drive_names: list[str],
                       stamp_ns: np.ndarray, interior_angle_rad: np.ndarray, convex: np.ndarray,
                       scatter_per_drive: bool = False, pass_rho: float | None = None,
                       pose_shared_per_pass: bool = False, pass_shared_fraction: float = 0.0) -> ClusterSummary:
    """Summarise observations grouped by ``labels`` (0..K-1); ``drive_code`` indexes ``drive_names``;
    ``scatter_per_drive``: the empirical extraction part counts one independent sample per drive, or, with
    ``pass_rho`` (the lag-1 correlation of a pass's observations, ``lag_one_correlation``), each drive's
    ``effective_samples`` of its observations plus a part shared by the pass whose variance is
    ``pass_shared_fraction`` of the views' own (``pass_mean_factor``)."""
    k = int(labels.max()) + 1 if len(labels) else 0
    n_obs = np.bincount(labels, minlength=k)

    # Directions: align each pair to the first observation of its cluster, then circular means.
    first = np.full(k, len(labels))
    np.minimum.at(first, labels, np.arange(len(labels)))
    _, swapped = pair_difference_rad(obs.theta_enu_rad[first][labels], obs.theta_enu_rad)
    aligned = np.where(swapped[:, None], obs.theta_enu_rad[:, ::-1], obs.theta_enu_rad)
    t1, r1 = circular_mean_by_label(aligned[:, 0], labels, k)
    t2, r2 = circular_mean_by_label(aligned[:, 1], labels, k)
    theta = canonicalize_pairs(np.column_stack([t1, t2]))
    spread = np.sqrt(-2.0 * np.log(np.clip(np.minimum(r1, r2), 1e-12, 1.0)))

    # Position: information-weighted mean.
    W = _inv_spd(obs.cov_m2)
    W_sum = _sum2x2(labels, W, k)
    Wx_sum = _sum2(labels, np.einsum("nij,nj->ni", W, obs.en_m), k)
    en = np.linalg.solve(W_sum, Wx_sum[..., None])[..., 0]

    d = obs.en_m - en[labels]
    scatter = _sum2x2(labels, d[:, :, None] * d[:, None, :], k) / np.maximum(n_obs - 1, 1)[:, None, None]

    # Drives seen.
    pairs = np.unique(np.column_stack([labels, drive_code]), axis=0)
    n_drives = np.bincount(pairs[:, 0], minlength=k).astype(np.int32)
    split_at = np.cumsum(n_drives)[:-1]
    drives = [",".join(drive_names[c] for c in codes) for codes in np.split(pairs[:, 1], split_at)] if k else []

    if pose_shared_per_pass and obs.J_pose is not None:
        cov_pose_mean = shared_pose_part(labels, drive_code, obs, W, W_sum, k)
    else:
        cov_pose_mean = _sum2x2(labels, obs.cov_pose_m2, k) / n_obs[:, None, None] / n_drives[:, None, None]
    extract_info = np.linalg.inv(_sum2x2(labels, _inv_spd(obs.cov_corner_m2), k))

    def extraction_part(se_factor: np.ndarray) -> np.ndarray:
        standard_error = scatter * se_factor[:, None, None]
        use_empirical = np.trace(standard_error, axis1=1, axis2=2) > np.trace(extract_info, axis1=1, axis2=2)
        return np.where(use_empirical[:, None, None], standard_error, extract_info)

    extract_mean = extraction_part(1.0 / n_obs)
    if scatter_per_drive and pass_rho is not None:
        per_pass = np.unique(np.column_stack([labels, drive_code]), axis=0, return_counts=True)
        n_eff = np.bincount(per_pass[0][:, 0], effective_samples(per_pass[1], pass_rho), minlength=k)
        se = pass_mean_factor(n_obs, n_eff, n_drives, pass_shared_fraction)
    else:
        se = 1.0 / (n_drives if scatter_per_drive else n_obs)
    cov_map = cov_pose_mean + extraction_part(np.broadcast_to(se, (k,)).astype(float))
    cov_map = 0.5 * (cov_map + cov_map.transpose(0, 2, 1)) + _COV_FLOOR_M2 * np.eye(2)

    first_seen = np.full(k, np.iinfo(np.int64).max)
    last_seen = np.full(k, np.iinfo(np.int64).min)
    np.minimum.at(first_seen, labels, stamp_ns)
    np.maximum.at(last_seen, labels, stamp_ns)
    interior, _ = circular_mean_by_label(np.asarray(interior_angle_rad, float), labels, k)
    convex_share = np.bincount(labels, np.asarray(convex, float), minlength=k) / np.maximum(n_obs, 1)
    return ClusterSummary(
        en_m=en, theta_rad=theta, cov_map_m2=cov_map, cov_scatter_m2=scatter, angle_spread_rad=spread,
        n_obs=n_obs.astype(np.int64), n_drives=n_drives, drives=drives, first_seen_ns=first_seen,
        last_seen_ns=last_seen, interior_angle_rad=np.mod(interior, 2.0 * np.pi), convex=convex_share >= 0.5,
        cov_pose_m2=cov_pose_mean, cov_extract_mean_m2=extract_mean,
    )


def largest_std_m(cov_m2: np.ndarray) -> np.ndarray:
    """(K,2,2) -> (K,) square root of the largest eigenvalue."""
    return np.sqrt(np.clip(np.linalg.eigvalsh(cov_m2)[:, -1], 0.0, None))

