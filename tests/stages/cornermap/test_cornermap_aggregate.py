"""Per-cluster statistics and the filter: oracle means, circular means across +-pi, SPD covariances."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.cornermap.aggregate import aggregate_clusters
from stages.cornermap.angles import canonicalize_pairs, pair_difference_rad
from stages.cornermap.filtering import FilterThresholds, reject_reasons
from stages.cornermap.transform import EnuObservations
from tests.stages.cornermap.cornermap_synth import scatter_enu, true_corners

TH = FilterThresholds(min_obs=8, min_drives=1, max_spread_m=0.15, max_cov_trace_m2=0.01,
                      max_angle_spread_rad=np.radians(6.0))


def _obs(en, theta, sigma_m=0.03, pose_m=0.02):
    n = len(en)
    return EnuObservations(en, canonicalize_pairs(theta), np.tile(np.eye(2) * sigma_m**2, (n, 1, 1)),
                           np.tile(np.eye(2) * pose_m**2, (n, 1, 1)))


def _aggregate(labels, obs, drive_code=None):
    n = len(labels)
    code = np.zeros(n, np.int64) if drive_code is None else drive_code
    return aggregate_clusters(labels, obs, code, ["d0", "d1", "d2"], np.arange(n, dtype=np.int64) * 10,
                              np.full(n, np.pi / 2), np.ones(n, bool))


def test_means_recover_the_known_corners():
    corners = true_corners()
    en, theta, truth = scatter_enu(corners, n_per=200, seed=21)
    s = _aggregate(truth, _obs(en, theta))
    np.testing.assert_allclose(s.en_m, corners[:, :2], atol=3 * 0.03 / np.sqrt(200) * 2)
    diff, swapped = pair_difference_rad(s.theta_rad, canonicalize_pairs(corners[:, 2:]))
    assert np.all(np.degrees(diff) < 0.3) and not swapped.any()
    assert np.all(s.n_obs == 200) and s.first_seen_ns[1] == 200 * 10 and s.last_seen_ns[1] == 399 * 10
    sigma_scatter = np.sqrt(s.cov_scatter_m2[:, [0, 1], [0, 1]])
    np.testing.assert_allclose(sigma_scatter, 0.03, rtol=0.2)  # 4 sigma of a 200-sample std
    assert np.all(np.array(reject_reasons(s, TH)) == "")


def test_map_covariance_pose_part_shrinks_with_drives_not_with_scans():
    en, theta, _ = scatter_enu(true_corners()[:1], n_per=300, seed=22, sigma_m=0.001)
    labels = np.zeros(300, np.int64)
    one = _aggregate(labels, _obs(en, theta, sigma_m=0.001, pose_m=0.05))
    three = _aggregate(labels, _obs(en, theta, sigma_m=0.001, pose_m=0.05), np.arange(300) % 3)
    assert one.n_drives[0] == 1 and three.n_drives[0] == 3 and three.drives[0] == "d0,d1,d2"
    np.testing.assert_allclose(one.cov_map_m2[0, 0, 0], 0.05**2, rtol=0.05)
    np.testing.assert_allclose(three.cov_map_m2[0, 0, 0], 0.05**2 / 3, rtol=0.05)


def test_filter_names_each_reason():
    rng = np.random.default_rng(23)
    en = np.vstack([rng.normal([0, 0], 0.02, (3, 2)),  # few observations
                    rng.normal([10, 0], 0.4, (50, 2)),  # wide scatter
                    rng.normal([20, 0], 0.02, (50, 2)),  # walls disagree
                    rng.normal([30, 0], 0.02, (50, 2))])  # good
    theta = np.tile([0.0, np.pi / 2], (len(en), 1))
    theta[53:103, 1] += rng.normal(0.0, np.radians(15.0), 50)
    labels = np.repeat([0, 1, 2, 3], [3, 50, 50, 50])
    reasons = reject_reasons(_aggregate(labels, _obs(en, theta)), TH)
    assert reasons[0].startswith("few_observations: 3 < 8")
    assert reasons[1].startswith("large_spread") and "large_covariance" not in reasons[0]
    assert reasons[2].startswith("angle_spread")
    assert reasons[3] == ""


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 30), degenerate=st.booleans())
def test_kept_clusters_always_have_an_spd_covariance(seed, n, degenerate):
    """Random (also singular or collinear) inputs: anything the filter keeps is symmetric positive definite."""
    rng = np.random.default_rng(seed)
    en = np.column_stack([rng.normal(0, 0.05, n), np.zeros(n) if degenerate else rng.normal(0, 0.05, n)])
    a = rng.normal(0, 0.05, (n, 2, 2))
    cov = a @ a.transpose(0, 2, 1) * (0.0 if degenerate else 1.0)  # singular when degenerate
    obs = EnuObservations(en, canonicalize_pairs(np.tile([0.0, 1.5], (n, 1))), cov, np.zeros((n, 2, 2)))
    s = _aggregate(np.zeros(n, np.int64), obs)
    th = FilterThresholds(1, 1, 10.0, 10.0, 1.0)
    for cov_map, reason in zip(s.cov_map_m2, reject_reasons(s, th)):
        if reason == "":
            np.testing.assert_allclose(cov_map, cov_map.T)
            assert np.linalg.eigvalsh(cov_map)[0] > 0.0
            np.linalg.cholesky(cov_map)


def test_non_finite_covariance_is_rejected_not_stored():
    en, theta, _ = scatter_enu(true_corners()[:1], n_per=20, seed=24)
    obs = _obs(en, theta)
    bad = EnuObservations(obs.en_m, obs.theta_enu_rad, obs.cov_corner_m2, obs.cov_pose_m2.copy())
    bad.cov_pose_m2[0] = np.nan
    s = _aggregate(np.zeros(20, np.int64), bad)
    assert reject_reasons(s, TH)[0].startswith("non_positive_definite")


def _pass_errors(rng, n_clusters: int, n_per: int, sigma_m: float, rho: float) -> np.ndarray:
    """(n_clusters, n_per, 2) extraction errors along one pass: AR(1) from scan to scan (correlation ``rho``),
    stationary std ``sigma_m`` per axis: consecutive views of a corner share most of their error."""
    e = np.empty((n_clusters, n_per, 2))
    e[:, 0] = rng.normal(0, sigma_m, (n_clusters, 2))
    for i in range(1, n_per):
        e[:, i] = rho * e[:, i - 1] + np.sqrt(1 - rho**2) * rng.normal(0, sigma_m, (n_clusters, 2))
    return e


def test_scatter_counted_once_per_drive_keeps_the_map_covariance_honest_under_correlated_views():
    """300 corners, each seen in 40 scans of one pass whose extraction errors are correlated from scan to scan
    (AR(1), rho 0.95): the mean keeps most of the pass's error. Counting the scatter over the 40 observations
    claims a ~10x smaller std than the mean's error (NEES ~100x its 2); counting it once per drive leaves the NEES
    within a factor 3 of 2 (the scatter of strongly correlated views understates their error). Two independent
    passes halve the per-drive part."""
    rng = np.random.default_rng(31)
    k, n_per, sigma = 300, 40, 0.03
    truth = rng.uniform(-500, 500, (k, 2))
    labels = np.repeat(np.arange(k), n_per)
    en = (truth[:, None, :] + _pass_errors(rng, k, n_per, sigma, 0.95)).reshape(-1, 2)
    theta = np.tile([0.0, np.pi / 2], (k * n_per, 1))
    obs = _obs(en, theta, sigma_m=0.001, pose_m=0.0001)
    code = np.zeros(k * n_per, np.int64)
    nees = {}
    for per_drive in (False, True):
        s = aggregate_clusters(labels, obs, code, ["d0"], np.arange(k * n_per, dtype=np.int64),
                               np.full(k * n_per, np.pi / 2), np.ones(k * n_per, bool), scatter_per_drive=per_drive)
        r = s.en_m - truth
        nees[per_drive] = float(np.mean(np.einsum("ni,ni->n", r, np.linalg.solve(s.cov_map_m2, r[..., None])[..., 0])))
        # the quality filter judges the same quantity either way
        np.testing.assert_allclose(s.cov_extract_mean_m2, s.cov_scatter_m2 / n_per, rtol=1e-9)
    assert nees[False] > 100.0 and 1.0 < nees[True] < 6.0, nees
    two = aggregate_clusters(labels, obs, np.arange(k * n_per) % 2, ["d0", "d1"], np.arange(k * n_per, dtype=np.int64),
                             np.full(k * n_per, np.pi / 2), np.ones(k * n_per, bool), scatter_per_drive=True)
    np.testing.assert_allclose(two.cov_map_m2 - two.cov_pose_m2,
                               two.cov_scatter_m2 / 2 + 1e-8 * np.eye(2), rtol=1e-6)
