"""A pass's views share their errors: the lag-1 correlation measured on the passes, the effective number of
independent views, and the pose part through the weighted mean's Jacobian, each against a Monte-Carlo oracle."""
from __future__ import annotations

import numpy as np

from stages.cornermap.aggregate import aggregate_clusters, effective_samples, lag_one_correlation
from stages.cornermap.angles import canonicalize_pairs
from stages.cornermap.transform import EnuObservations, transform_to_enu


def _ar1(rng, n, rho, sigma):
    """(n,2) a stationary AR(1) sequence with lag-1 correlation ``rho`` and marginal std ``sigma`` per axis."""
    e = np.empty((n, 2))
    e[0] = rng.normal(size=2) * sigma
    innov = sigma * np.sqrt(1.0 - rho**2)
    for k in range(1, n):
        e[k] = rho * e[k - 1] + rng.normal(size=2) * innov
    return e


def _passes(rng, k, n, rho, sigma):
    labels = np.repeat(np.arange(k), n)
    centres = rng.uniform(-100, 100, (k, 2))
    en = centres[labels] + np.concatenate([_ar1(rng, n, rho, sigma) for _ in range(k)])
    return labels, en, np.tile(np.arange(n, dtype=np.int64), k), centres


def test_lag_one_correlation_recovers_the_sequence_correlation():
    rng = np.random.default_rng(3)
    for rho in (0.0, 0.5, 0.8):
        labels, en, stamp, _ = _passes(rng, 40, 40, rho, 0.03)
        est, pairs = lag_one_correlation(labels, np.zeros(len(labels), np.int64), stamp, en)
        assert pairs == 40 * 39
        # the deviations are about each pass's own mean: biased low by about (1 + rho) / n
        assert abs(est - rho) < 0.05, (rho, est)


def test_effective_samples_state_the_spread_of_a_pass_mean():
    """The standard error ``scatter / n_eff`` matches the spread of AR(1) pass means over many passes, where one
    sample per pass (scatter / 1) overstates it and one per view (scatter / n) understates it."""
    rng = np.random.default_rng(5)
    k, n, rho, sigma = 400, 40, 0.8, 0.03
    labels, en, stamp, centres = _passes(rng, k, n, rho, sigma)
    code = np.zeros(len(labels), np.int64)
    est, _ = lag_one_correlation(labels, code, stamp, en)
    obs = EnuObservations(en, canonicalize_pairs(np.tile([0.0, 1.5], (len(en), 1))),
                          np.tile(np.eye(2) * 1e-6, (len(en), 1, 1)), np.zeros((len(en), 2, 2)))
    common = (labels, obs, code, ["d0"], stamp, np.full(len(en), np.pi / 2), np.ones(len(en), bool))
    err = aggregate_clusters(*common, scatter_per_drive=True).en_m - centres
    true_var = float(np.mean(err**2))
    stated = {name: float(np.mean(aggregate_clusters(*common, **kw).cov_map_m2[:, [0, 1], [0, 1]]))
              for name, kw in (("pass", dict(scatter_per_drive=True)),
                               ("ar1", dict(scatter_per_drive=True, pass_rho=est)),
                               ("views", dict(scatter_per_drive=False)))}
    assert 0.7 < stated["ar1"] / true_var < 1.45, (stated, true_var)
    assert stated["pass"] / true_var > 3.0 and stated["views"] / true_var < 0.5
    np.testing.assert_allclose(effective_samples(np.array([1, 10, 100]), 0.0), [1, 10, 100])
    np.testing.assert_allclose(effective_samples(np.array([1, 10, 100]), 0.99), [1, 1, 1])


def test_shared_pose_error_acts_through_the_mean_lever_arm():
    """A corner 10 m beside a straight road, seen from 40 m before to 40 m after it, every view's pose off by one
    error common to the pass (0.02 m, 0.1 deg): the Monte-Carlo spread of the cluster mean (the views placed with
    the displaced poses, aggregated again) matches the shared model; the average of the views' own propagated
    covariances overstates the along-road part, where the lever arms of views ahead and behind cancel in the mean."""
    rng = np.random.default_rng(11)
    x = np.linspace(-40.0, 40.0, 41)
    n = len(x)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = x
    corner_lidar = np.column_stack([-x, np.full(n, 10.0)])  # the corner at (0, 10) in every view
    theta = np.tile([0.0, 1.5], (n, 1))
    sig = np.diag([0.02**2, 0.02**2, np.radians(0.1) ** 2])
    cov_lidar = np.tile(np.eye(2) * 0.01**2, (n, 1, 1))

    def aggregate(obs, labels, **kw):
        m = len(labels)
        return aggregate_clusters(labels, obs, np.zeros(m, np.int64), ["d0"], np.arange(m, dtype=np.int64),
                                  np.full(m, np.pi / 2), np.ones(m, bool), scatter_per_drive=True, **kw)

    obs = transform_to_enu(corner_lidar, theta, cov_lidar, T, np.eye(4), np.tile(sig, (n, 1, 1)))
    one = np.zeros(n, np.int64)
    shared = aggregate(obs, one, pose_shared_per_pass=True).cov_pose_m2[0]
    averaged = aggregate(obs, one).cov_pose_m2[0]
    k = 1500
    d = rng.multivariate_normal(np.zeros(3), sig, size=k)
    Tk = np.repeat(T[None], k, axis=0)
    c, s_ = np.cos(d[:, 2]), np.sin(d[:, 2])
    R = np.zeros((k, 4, 4))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2], R[:, 3, 3] = c, -s_, s_, c, 1.0, 1.0
    Tk = Tk @ R[:, None]  # the heading error turns each view about its own vehicle
    Tk[:, :, 0, 3] += d[:, 0, None]
    Tk[:, :, 1, 3] += d[:, 1, None]
    moved = transform_to_enu(np.tile(corner_lidar, (k, 1)), np.tile(theta, (k, 1)), np.tile(cov_lidar, (k, 1, 1)),
                             Tk.reshape(-1, 4, 4), np.eye(4), np.tile(sig, (k * n, 1, 1)))
    means = aggregate(moved, np.repeat(np.arange(k), n)).en_m
    np.testing.assert_allclose(np.cov(means.T), shared, rtol=0.08, atol=2e-5)
    assert averaged[1, 1] > 3.0 * shared[1, 1]  # along the road: the lever arms ahead and behind cancel


def test_a_part_shared_by_the_pass_is_stated_beside_the_ar1_part():
    """Passes whose views' errors are a constant part shared by the pass (var f s^2, it does not scatter) plus an
    AR(1) part (var s^2, rho 0.7): with ``pass_shared_fraction`` f the stated variance of a pass mean matches the
    Monte-Carlo spread of the means; without it (the AR(1) count alone) it understates that spread by about the
    shared part. With two drives per corner (independent passes) the shared part halves."""
    rng = np.random.default_rng(17)
    k, n, rho, sigma, f = 400, 40, 0.7, 0.03, 0.25

    def views(n_drives):
        labels = np.repeat(np.arange(k), n * n_drives)
        code = np.tile(np.repeat(np.arange(n_drives), n), k)
        centres = rng.uniform(-100, 100, (k, 2))
        shared = rng.normal(size=(k * n_drives, 2)) * sigma * np.sqrt(f)
        err = np.concatenate([_ar1(rng, n, rho, sigma) for _ in range(k * n_drives)]) + np.repeat(shared, n, axis=0)
        en = centres[labels] + err
        stamp = np.tile(np.arange(n * n_drives, dtype=np.int64), k)
        return labels, code, stamp, en, centres

    for n_drives in (1, 2):
        labels, code, stamp, en, centres = views(n_drives)
        est, _ = lag_one_correlation(labels, code, stamp, en)
        assert abs(est - rho) < 0.06, est  # the shared part does not show in the deviations from the pass mean
        obs = EnuObservations(en, canonicalize_pairs(np.tile([0.0, 1.5], (len(en), 1))),
                              np.tile(np.eye(2) * 1e-6, (len(en), 1, 1)), np.zeros((len(en), 2, 2)))
        common = (labels, obs, code, [f"d{i}" for i in range(n_drives)], stamp, np.full(len(en), np.pi / 2),
                  np.ones(len(en), bool))
        s = aggregate_clusters(*common, scatter_per_drive=True, pass_rho=est, pass_shared_fraction=f)
        true_var = float(np.mean((s.en_m - centres) ** 2))
        stated = float(np.mean(s.cov_map_m2[:, [0, 1], [0, 1]]))
        without = float(np.mean(aggregate_clusters(*common, scatter_per_drive=True, pass_rho=est)
                                .cov_map_m2[:, [0, 1], [0, 1]]))
        assert 0.8 < stated / true_var < 1.25, (n_drives, stated, true_var)
        assert without / true_var < 0.6, (n_drives, without, true_var)


def test_pass_mean_factor_reduces_to_the_ar1_count_and_caps_it():
    from stages.cornermap.aggregate import pass_mean_factor

    n, n_eff, d = np.array([40.0, 40.0, 5.0]), np.array([8.0, 8.0, 1.0]), np.array([1, 2, 1])
    np.testing.assert_allclose(pass_mean_factor(n, n_eff, d), [39 / (40 * 7), 39 / (40 * 7), 1.0])
    var_a = 39 * 8 / (40 * 7)
    np.testing.assert_allclose(pass_mean_factor(n, n_eff, d, 0.5), [39 / 280 + 0.5 * var_a, 39 / 280 + 0.25 * var_a,
                                                                     1.5])
