"""GNSS (RTK/INS or a consumer receiver) and odometry error models.

Horizontal GNSS/INS error = slowly varying bias (first-order Gauss-Markov, std growing with the fraction of
sky blocked by buildings) + white noise + multipath jumps of 1-2 m lasting seconds (more likely in
canyons) + short outages (rows omitted). The bias is scaled so that its RMS over the drive equals the
preset's target (the calibration to Im et al.'s reported RTK/INS behaviour); its time shape and canyon
dependence are kept. Reported standard deviations understate the error in canyons, as receivers do.
A consumer receiver (presets ``*_consumer``): metres of bias with a correlation time of minutes, larger jumps,
longer outages, a reported std of the order of the bias, and without an INS the heading is the course over
ground (``course_over_ground_errors``: velocity noise over speed, held while standing) with no roll or pitch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.mesh import Scene

GNSS_RATE_HZ = 20.0


def sky_blocked_fraction(buildings: Scene, antenna_enu: np.ndarray) -> np.ndarray:
    """(N, 3) antenna positions -> (N,) solid-angle-weighted fraction of the sky (elevation > 5 deg) blocked."""
    az = np.radians(np.arange(0, 360, 10.0))
    el = np.radians(np.arange(10.0, 90.0, 10.0))
    A, E = np.meshgrid(az, el)
    dirs = np.column_stack([(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(), np.sin(E).ravel()])
    w = np.cos(E).ravel()
    n, m = len(antenna_enu), len(dirs)
    t_hit, _ = buildings.cast(np.repeat(antenna_enu, m, axis=0), np.tile(dirs, (n, 1)))
    blocked = np.isfinite(t_hit).reshape(n, m)
    return blocked @ w / w.sum()


def gauss_markov(n: int, dt_s: float, tau_s: float, rng: np.random.Generator, dims: int = 1) -> np.ndarray:
    """Unit-variance first-order Gauss-Markov process, stationary from the start: (n, dims)."""
    from scipy.signal import lfilter

    a = np.exp(-dt_s / tau_s)
    w = rng.normal(size=(n, dims)) * np.sqrt(1 - a * a)
    w[0] = rng.normal(size=dims)
    return lfilter([1.0], [1.0, -a], w, axis=0)


@dataclass(frozen=True)
class GnssErrors:
    err_enu_m: np.ndarray  # (N, 3) reported minus true position
    err_yaw_rad: np.ndarray  # (N,)
    err_roll_rad: np.ndarray
    err_pitch_rad: np.ndarray
    std_enu_m: np.ndarray  # (N, 3) reported
    std_yaw_rad: np.ndarray  # (N,) reported
    valid: np.ndarray  # (N,) False inside outages (rows not written)


def simulate_gnss_errors(t_s: np.ndarray, canyon: np.ndarray, dist_m: np.ndarray, target_rms_m: float,
                         bias_open_m: float, bias_canyon_m: float, multipath_per_km: float, outage_per_km: float,
                         rng: np.random.Generator, *, bias_tau_s: float = 90.0,
                         multipath_m: tuple[float, float] = (1.0, 1.8), outage_s: tuple[float, float] = (1.5, 5.0),
                         std_share: float = 0.0) -> GnssErrors:
    """Errors at the GNSS epochs ``t_s`` given the blocked-sky fraction and distance driven at each epoch.

    ``bias_tau_s``: correlation time of the bias; ``multipath_m`` / ``outage_s``: size of a multipath jump and
    length of an outage; ``std_share`` 0: the RTK/INS reported std (understated in canyons), > 0: the reported
    horizontal std is this share of the bias std at the epoch (a consumer receiver's estimate, metres)."""
    from scipy.ndimage import uniform_filter1d

    n = len(t_s)
    dt = float(t_s[1] - t_s[0])
    c = uniform_filter1d(canyon, size=max(1, int(10.0 / dt)), mode="nearest")
    sigma_b = bias_open_m + bias_canyon_m * c
    bias = gauss_markov(n, dt, bias_tau_s, rng, 2) * sigma_b[:, None] / np.sqrt(2)
    scale = target_rms_m / np.sqrt(np.mean(np.sum(bias ** 2, axis=1)))
    bias *= scale
    sigma_b = sigma_b * scale
    white = rng.normal(size=(n, 2)) * (0.02 + 0.08 * c)[:, None]
    up = gauss_markov(n, dt, 120.0, rng)[:, 0] * 1.4 * sigma_b / np.sqrt(2) + rng.normal(size=n) * 0.04
    km = float(dist_m[-1] - dist_m[0]) / 1000.0
    weight = 0.15 + c
    multipath = np.zeros((n, 2))
    for _ in range(rng.poisson(multipath_per_km * km)):
        k0 = rng.choice(n, p=weight / weight.sum())
        dur = rng.uniform(2.0, 8.0)
        mag = rng.uniform(*multipath_m)
        ang = rng.uniform(0, 2 * np.pi)
        tt = t_s - t_s[k0]
        ramp = np.clip(np.minimum(tt / 0.5, (dur - tt) / 0.5), 0.0, 1.0)  # trapezoid, 0.5 s edges
        multipath += ramp[:, None] * mag * np.array([np.cos(ang), np.sin(ang)])
    valid = np.ones(n, bool)
    for _ in range(rng.poisson(outage_per_km * km)):
        k0 = rng.choice(n, p=weight / weight.sum())
        valid &= ~((t_s >= t_s[k0]) & (t_s < t_s[k0] + rng.uniform(*outage_s)))
    err_h = bias + white + multipath
    yaw_sigma = np.radians(0.15 + 0.25 * c)
    err_yaw = gauss_markov(n, dt, 60.0, rng)[:, 0] * yaw_sigma + rng.normal(size=n) * np.radians(0.03)
    in_mp = np.linalg.norm(multipath, axis=1) > 0.1
    if std_share > 0:  # of the order of the target bias, higher in canyons (the scaled sigma_b is not: over a drive
        # much shorter than the bias' correlation time the normalisation to the target RMS scales it arbitrarily)
        shape = (bias_open_m + bias_canyon_m * c) / np.mean(bias_open_m + bias_canyon_m * c)
        std_h = (0.05 + std_share * target_rms_m / np.sqrt(2) * shape) * np.where(in_mp, 1.5, 1.0)
    else:
        std_h = (0.012 + 0.3 * bias_open_m * scale + 0.12 * sigma_b * c) * np.where(in_mp, 1.5, 1.0)
    std = np.column_stack([std_h * 0.95, std_h * 1.05, 1.6 * std_h])
    return GnssErrors(np.column_stack([err_h, up]), err_yaw, rng.normal(size=n) * np.radians(0.02),
                      rng.normal(size=n) * np.radians(0.02), std, np.radians(0.05 + 0.08 * c), valid)


def simulate_odometry(speed_mps: np.ndarray, yaw_rate_radps: np.ndarray, dt_s: float,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Wheel speed with scale error and noise; gyro yaw rate with scale error, drifting bias and noise."""
    n = len(speed_mps)
    wheel = speed_mps * (1 + rng.normal(0, 0.01)) + rng.normal(0, 0.03, n) * (speed_mps > 0.05)
    wheel = np.maximum(np.round(wheel, 3), 0.0)
    bias = rng.normal(0, 0.002) + 0.0005 * gauss_markov(n, dt_s, 300.0, rng)[:, 0]
    gyro = yaw_rate_radps * (1 + rng.normal(0, 0.005)) + bias + rng.normal(0, 0.003, n)
    return wheel, gyro


COG_VELOCITY_SIGMA_MPS = 0.05  # a receiver's Doppler velocity noise per horizontal axis
COG_MIN_SPEED_MPS = 0.5  # below this a receiver holds its last course
COG_STANDING_STD_DEG = 45.0  # the course std it reports while holding


def course_over_ground_errors(speed_mps: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N,) speed at the epochs -> heading error of the course over ground (rad) and its reported std (rad).

    The course is the direction of the Doppler velocity: its error is N(0, sigma_v / speed) (0.29 deg at 10 m/s,
    1.4 deg at 2 m/s); below ``COG_MIN_SPEED_MPS`` the receiver holds the last course (the vehicle does not turn
    while standing, so the held error is the last one) and reports a large std."""
    speed = np.asarray(speed_mps, float)
    moving = speed >= COG_MIN_SPEED_MPS
    err = rng.normal(size=len(speed)) * COG_VELOCITY_SIGMA_MPS / np.maximum(speed, COG_MIN_SPEED_MPS)
    idx = np.where(moving, np.arange(len(speed)), 0)
    np.maximum.accumulate(idx, out=idx)  # index of the last moving epoch (0 before the first)
    err = np.where(moving, err, err[idx])
    std = np.where(moving, COG_VELOCITY_SIGMA_MPS / np.maximum(speed, COG_MIN_SPEED_MPS),
                   np.radians(COG_STANDING_STD_DEG))
    return err, std
