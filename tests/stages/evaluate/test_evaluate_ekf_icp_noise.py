"""Oracle tests of the ICP heading noise the corner EKF states per scan (``ekf.icp.registration_yaw_scale``).

Two drives whose ICP heading increments carry white noise of known, different std (one scene registers 4x better
than the other) and whose registration states that std up to one common factor (as odometry's point-to-plane
Hessian at a fixed point std does). Monte-Carlo over many draws of the noise, the heading error the filter's
prediction reaches is compared with the variance it states: with the registration's figure times the factor the mean
NEES of the heading is inside its chi-square band on both drives; one fixed std per scan (the params' sigma_yaw_deg)
is pessimistic on the better drive and optimistic on the worse.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from stages.evaluate.localize_ekf import CornerMap, CornerObservations, icp_yaw_sigma_rad, increment_covariance, run_ekf
from tests.stages.evaluate.ekf_settings import bare_ekf

N_EPOCHS = 200
N_RUNS = 2000
SCALE = 2.5  # the registration's stated std (its floor aside) is the truth's / SCALE
FLOOR_RAD = 1e-4  # odometry's information.min_sigma_rad, in every edge's stated covariance


def no_corners() -> tuple[CornerObservations, CornerMap]:
    return (
        CornerObservations(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2))),
        CornerMap(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2))),
    )


def heading_nees(true_sigma_deg: np.ndarray, cfg, seed: int) -> float:
    """Mean over runs of the last epoch's heading NEES (1 dof) of a straight 0.5 m-per-scan drive. Without corners
    the filter's heading is the sum of the increments' and its stated variance does not depend on the draw: the
    filter runs on one draw (its heading checked against that sum), the other draws are summed directly."""
    rng = np.random.default_rng(seed)
    obs, cmap = no_corners()
    sig = np.deg2rad(true_sigma_deg)
    cov = np.zeros((N_EPOCHS, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = 1e-6
    cov[:, 2, 2] = (sig / SCALE) ** 2 + FLOOR_RAD**2  # what the registration states: its Hessian and odometry's floor
    P0 = np.diag([1e-4, 1e-4, 1e-10])
    noise = rng.normal(0.0, sig[1:], size=(N_RUNS, N_EPOCHS - 1))  # the truth drives straight east
    inc = np.zeros((N_EPOCHS, 3))
    inc[1:, 0] = 0.5
    inc[1:, 2] = noise[0]
    r = run_ekf(inc, obs, cmap, np.zeros(3), P0, 0, cfg, icp_cov=cov)
    assert np.isclose(r.q[-1, 2], noise[0].sum(), atol=1e-9)
    return float(np.mean(noise.sum(axis=1) ** 2) / r.P[-1, 2, 2])


def band(runs: int = N_RUNS, confidence: float = 0.999) -> tuple[float, float]:
    a = (1.0 - confidence) / 2.0
    return chi2.ppf(a, runs) / runs, chi2.ppf(1.0 - a, runs) / runs


def test_registration_scaled_heading_noise_is_consistent_on_a_good_and_a_poor_scene():
    lo, hi = band()
    scaled = bare_ekf(icp={"sigma_yaw_frac": 0.0, "registration_yaw_scale": SCALE})
    fixed = bare_ekf(icp={"sigma_yaw_frac": 0.0, "sigma_yaw_deg": 0.016, "registration_yaw_scale": 0.0})
    good = np.full(N_EPOCHS, 0.007)  # demo's facades: 0.007-0.008 deg per scan
    poor = np.full(N_EPOCHS, 0.028)
    for sigma, seed in ((good, 1), (poor, 2)):
        assert lo < heading_nees(sigma, scaled, seed) < hi
    assert heading_nees(good, fixed, 3) < lo  # 0.016 stated for 0.007 real: pessimistic
    assert heading_nees(poor, fixed, 4) > hi  # 0.016 stated for 0.028 real: optimistic


def test_scan_by_scan_noise_follows_the_registration():
    """A drive whose scenes alternate (good and poor stretches of 20 scans): the stated variance follows each scan."""
    lo, hi = band()
    sigma = np.where((np.arange(N_EPOCHS) // 20) % 2 == 0, 0.005, 0.03)
    cfg = bare_ekf(icp={"sigma_yaw_frac": 0.0, "registration_yaw_scale": SCALE})
    assert lo < heading_nees(sigma, cfg, 5) < hi


def test_the_fixed_std_where_the_registration_states_none():
    cfg = bare_ekf(icp={"sigma_yaw_frac": 0.0, "sigma_yaw_deg": 0.016, "registration_yaw_scale": 2.0})
    nan = np.full((3, 3), np.nan)
    assert icp_yaw_sigma_rad(None, cfg) == np.deg2rad(0.016)
    assert icp_yaw_sigma_rad(nan, cfg) == np.deg2rad(0.016)
    assert icp_yaw_sigma_rad(np.zeros((3, 3)), cfg) == np.deg2rad(0.016)
    stated = np.diag([1e-6, 1e-6, np.deg2rad(0.004) ** 2 + FLOOR_RAD**2])
    assert np.isclose(icp_yaw_sigma_rad(stated, cfg), np.deg2rad(0.008))
    no_floor = bare_ekf(icp={"registration_yaw_scale": 2.0, "registration_yaw_floor_deg": 0.0})
    assert np.isclose(icp_yaw_sigma_rad(stated, no_floor), 2.0 * np.sqrt(stated[2, 2]))
    off = bare_ekf(icp={"sigma_yaw_deg": 0.016, "registration_yaw_scale": 0.0})
    assert icp_yaw_sigma_rad(stated, off) == np.deg2rad(0.016)
    # the translation part does not follow the registration (the wheel_bias model adds the registration's own)
    Q = increment_covariance(np.array([0.5, 0.0, 0.0]), cfg, stated)
    assert np.allclose(Q[:2, :2], increment_covariance(np.array([0.5, 0.0, 0.0]), cfg)[:2, :2])
