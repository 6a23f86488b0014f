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


def aggregate_clusters(labels: np.ndarray, obs: EnuObservations, drive_code: np.ndarray, drive_names: list[str],
                       stamp_ns: np.ndarray, interior_angle_rad: np.ndarray, convex: np.ndarray,
                       scatter_per_drive: bool = False) -> ClusterSummary:
    """Summarise observations grouped by ``labels`` (0..K-1); ``drive_code`` indexes ``drive_names``;
    ``scatter_per_drive``: the empirical extraction part counts one independent sample per drive."""
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

    cov_pose_mean = _sum2x2(labels, obs.cov_pose_m2, k) / n_obs[:, None, None] / n_drives[:, None, None]
    extract_info = np.linalg.inv(_sum2x2(labels, _inv_spd(obs.cov_corner_m2), k))

    def extraction_part(n_independent: np.ndarray) -> np.ndarray:
        standard_error = scatter / n_independent[:, None, None]
        use_empirical = np.trace(standard_error, axis1=1, axis2=2) > np.trace(extract_info, axis1=1, axis2=2)
        return np.where(use_empirical[:, None, None], standard_error, extract_info)

    extract_mean = extraction_part(n_obs)
    cov_map = cov_pose_mean + (extraction_part(n_drives) if scatter_per_drive else extract_mean)
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

