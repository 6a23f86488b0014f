"""Epoch loop of the road-marking MCL and the wheel-speed + gyro odometry it predicts with.

Epoch k is scan k of the evaluation drive. Feature points come as flat arrays tagged with their epoch, in the
vehicle frame. The marking raster is fetched window by window through a callable, as a vehicle streams tiles.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from stages.common.geometry import wrap_angle_rad
from stages.evaluate import mcl
from stages.evaluate.mcl_params import MarkingLikelihood, MclConfig

log = logging.getLogger(__name__)

RasterFetcher = Callable[[float, float, float, float], mcl.Raster]


@dataclass(frozen=True)
class MclRun:
    q: np.ndarray  # (E,3), NaN before initialisation
    P: np.ndarray  # (E,3,3)
    n_features: np.ndarray  # (E,) int
    calibration: np.ndarray | None = None  # (E,2) mean wheel scale and gyro bias [rad/s] (E,3: and gyro gain)
    ess: np.ndarray | None = None  # (E,) effective sample size after the update
    score: np.ndarray | None = None  # (E,) prior-weighted mean correlation score of the scan
    injected: np.ndarray | None = None  # (E,) particles injected before the update


def odometry_increments(odo_stamps_ns: np.ndarray, speed_mps: np.ndarray, yaw_rate_radps: np.ndarray,
                        epoch_stamps_ns: np.ndarray) -> np.ndarray:
    """Integrate wheel speed and gyro yaw rate (midpoint rule) and difference at the epochs.

    Returns (E,3) increments (dx, dy, dyaw) from epoch k-1 to k in the vehicle frame of epoch k-1; row 0 zero.
    """
    t = (np.asarray(odo_stamps_ns, dtype=np.int64) - int(odo_stamps_ns[0])) * 1e-9
    dt = np.diff(t)
    v = 0.5 * (speed_mps[1:] + speed_mps[:-1])
    w = 0.5 * (yaw_rate_radps[1:] + yaw_rate_radps[:-1])
    yaw = np.concatenate([[0.0], np.cumsum(w * dt)])
    yaw_mid = yaw[:-1] + 0.5 * w * dt
    x = np.concatenate([[0.0], np.cumsum(v * np.cos(yaw_mid) * dt)])
    y = np.concatenate([[0.0], np.cumsum(v * np.sin(yaw_mid) * dt)])
    te = (np.asarray(epoch_stamps_ns, dtype=np.int64) - int(odo_stamps_ns[0])) * 1e-9
    xe, ye, yawe = np.interp(te, t, x), np.interp(te, t, y), np.interp(te, t, yaw)
    inc = np.zeros((len(te), 3))
    c, s = np.cos(yawe[:-1]), np.sin(yawe[:-1])
    ddx, ddy = np.diff(xe), np.diff(ye)
    inc[1:, 0] = c * ddx + s * ddy
    inc[1:, 1] = -s * ddx + c * ddy
    inc[1:, 2] = np.diff(yawe)
    return inc


def _window_around(q: np.ndarray, fetch: RasterFetcher, cfg: MclConfig) -> mcl.Raster:
    half = 0.5 * cfg.window_m
    return fetch(q[0] - half, q[1] - half, q[0] + half, q[1] + half)


def _predict(particles: np.ndarray, calib: np.ndarray, increment: np.ndarray, step_m: float, dt_s: float,
             cfg: MclConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Wheel + gyro prediction through each particle's calibration, then the calibration's own random walk."""
    particles = mcl.predict_particles(particles, increment, cfg.sigma_frac, cfg.sigma_xy_m, cfg.sigma_yaw_rad, rng,
                                      calib, dt_s, cfg.sigma_lateral_frac, cfg.sigma_yaw_frac)
    walk = [cfg.sigma_scale_per_sqrt_m * np.sqrt(step_m), cfg.sigma_gyro_bias_rad_s_per_sqrt_s * np.sqrt(dt_s)]
    calib = calib + rng.standard_normal(calib.shape) * (walk + [0.0] * (calib.shape[1] - 2))  # the gain is constant
    return particles, calib


def _resample(particles: np.ndarray, calib: np.ndarray, weights: np.ndarray, cfg: MclConfig,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Low-variance resampling of poses and calibrations together, then roughening of the poses."""
    idx = mcl.low_variance_resample(weights, rng)
    particles = mcl.roughen(particles[idx], cfg.roughen_xy_m, cfg.roughen_yaw_rad, rng)
    return particles, calib[idx], np.full(cfg.n_particles, 1.0 / cfg.n_particles)


def _inject(particles: np.ndarray, calib: np.ndarray, weights: np.ndarray, share: float, feats: np.ndarray,
            raster: mcl.Raster, long_term_score: float, cfg: MclConfig, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Augmented MCL (Thrun et al. Table 8.3), local and guarded: when the scans fit the particles much worse than
    they used to, draw a share of candidate poses about the current estimate and let them replace as many particles
    only if the best of them fits the scan at ``inject_ratio`` of the long-term score and beats every particle by
    ``inject_margin`` of it. A wheel slip or a wrong dash leaves every particle off by more than the cloud's spread,
    which no reweighting recovers; an unmapped intersection or a periodic crosswalk lowers every pose's fit or lets
    a shifted pose fit about as well, and a lucky candidate there must not take over (on the demo drives the
    spurious winners led by <= 0.13 of the long-term score, the real recoveries by 0.23-0.35)."""
    m = int(round(share * cfg.n_particles))
    if m <= 0:
        return particles, calib, weights, 0
    q, _ = mcl.estimate(particles, weights)
    candidates = mcl.init_particles(q, cfg.recovery.inject_sigma_xy_m, cfg.recovery.inject_sigma_yaw_rad, m, rng)
    best = mcl.correlation_scores(candidates, feats, raster).max()
    current = mcl.correlation_scores(particles, feats, raster).max()
    log.debug("mcl injection test: best candidate %.3f, best particle %.3f, long-term %.3f", best, current,
              long_term_score)
    rec = cfg.recovery
    if best < rec.inject_ratio * long_term_score or best < current + rec.inject_margin * long_term_score:
        return particles, calib, weights, 0
    idx = rng.choice(cfg.n_particles, m, replace=False)
    particles, calib, weights = particles.copy(), calib.copy(), weights.copy()
    particles[idx] = candidates
    calib[idx] = calib[rng.choice(cfg.n_particles, m)]
    weights[idx] = 1.0 / cfg.n_particles
    return particles, calib, weights / weights.sum(), m


def _update(particles: np.ndarray, calib: np.ndarray, weights: np.ndarray, feats: np.ndarray, raster: mcl.Raster,
            alpha: float, cfg: MclConfig, likelihood: MarkingLikelihood, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Weight by ``alpha`` times the scan's log-likelihood; when that would leave fewer than ``min_ess_ratio * N``
    effective particles, apply it in pieces with a resample and a regularisation move in between."""
    log_w = np.log(np.maximum(weights, 1e-300))
    remaining = alpha
    min_ess = cfg.min_ess_ratio * cfg.n_particles
    prior_score = np.nan
    for piece in range(max(1, cfg.max_corrections)):
        scores = mcl.correlation_scores(particles, feats, raster)
        if piece == 0:
            prior_score = float(weights @ scores)
        loglik = mcl.log_likelihood(scores, len(feats), likelihood.sharpness, likelihood.effective_points)
        last = piece == cfg.max_corrections - 1
        beta = remaining if last else mcl.tempering_step(log_w, loglik, remaining, min_ess)
        weights = mcl.normalized_weights(log_w + beta * loglik)
        remaining -= beta
        if remaining <= 1e-9 * alpha:
            break
        idx = mcl.low_variance_resample(weights, rng)
        particles = mcl.regularize(particles[idx], rng, floor=(cfg.roughen_xy_m, cfg.roughen_xy_m, cfg.roughen_yaw_rad))
        calib = calib[idx]
        log_w = np.full(cfg.n_particles, -np.log(cfg.n_particles))
    return particles, calib, weights, prior_score


def run_mcl(increments: np.ndarray, feature_epoch: np.ndarray, features_vehicle_m: np.ndarray,
            fetch: RasterFetcher, q0: np.ndarray, start_epoch: int, rng: np.random.Generator,
            cfg: MclConfig = MclConfig(), stamps_ns: np.ndarray | None = None,
            likelihood: MarkingLikelihood = MarkingLikelihood(),
            init_spread: tuple[float, float] | None = None) -> MclRun:
    """Run the particle filter from ``start_epoch`` (particles drawn about q0) to the last epoch.

    Each epoch: predict with the wheel + gyro increment through every particle's calibration (a standstill holds
    the pose: a car does not turn in place, whatever the gyro bias integrates); weight by the correlation of the
    scan's features, tempered by the travel since the previous scan (overlapping scans repeat most of their
    evidence), in pieces when it is much narrower than the cloud (progressive correction); resample (low variance)
    when the effective sample size drops, then roughen. When the scans stop fitting, candidates about the estimate
    may replace some particles (guarded Augmented MCL). ``stamps_ns`` (E,) give the time steps of the gyro bias;
    without them every step is ``cfg.epoch_s``. ``likelihood``: the road markings' (``evaluate.markings``).
    ``init_spread``: the initial (position std m, heading std rad) instead of the section's (a start wider than
    the section states, e.g. by the map frame's error).
    """
    lk, rec = likelihood, cfg.recovery
    n = len(increments)
    q_out = np.full((n, 3), np.nan)
    P_out = np.full((n, 3, 3), np.nan)
    cal_out = np.full((n, 2 + (cfg.init_sigma_gyro_gain > 0)), np.nan)
    ess_out = np.full(n, np.nan)
    score_out = np.full(n, np.nan)
    n_feat = np.zeros(n, dtype=np.int32)
    off = np.searchsorted(feature_epoch, np.arange(n + 1))
    dt = np.full(n, cfg.epoch_s) if stamps_ns is None else np.r_[cfg.epoch_s, np.diff(stamps_ns) * 1e-9]
    init_xy_m, init_yaw_rad = init_spread or (cfg.init_sigma_xy_m, cfg.init_sigma_yaw_rad)
    particles = mcl.init_particles(q0, init_xy_m, init_yaw_rad, cfg.n_particles, rng)
    calib = mcl.init_calibration(cfg.n_particles, cfg.init_sigma_scale, cfg.init_sigma_gyro_bias_radps, rng,
                                 cfg.init_sigma_gyro_gain)
    weights = np.full(cfg.n_particles, 1.0 / cfg.n_particles)
    raster = _window_around(q0, fetch, cfg)
    margin = lk.feature_range_m + 3.0 * init_xy_m
    travel = np.inf  # since the last update; the first scan is a full measurement
    s_slow = s_fast = np.nan
    injected = np.zeros(n, dtype=np.int32)
    for k in range(start_epoch, n):
        step = float(np.hypot(increments[k, 0], increments[k, 1])) if k > start_epoch else 0.0
        if step >= cfg.standstill_m:
            particles, calib = _predict(particles, calib, increments[k], step, float(dt[k]), cfg, rng)
            travel += step
        feats = features_vehicle_m[off[k]:off[k + 1]]
        alpha = min(1.0, travel / lk.decorrelation_m) if lk.decorrelation_m > 0 else 1.0
        if len(feats) >= cfg.min_features and alpha > 0:
            lo, hi = particles[:, :2].min(axis=0) - margin, particles[:, :2].max(axis=0) + margin
            if not raster.contains(lo[0], lo[1], hi[0], hi[1]):
                raster = _window_around(np.average(particles, axis=0, weights=weights), fetch, cfg)
            if raster.observed is not None:
                feats = feats[mcl.observed_features(feats, mcl.estimate(particles, weights)[0], raster)]
        if len(feats) > lk.max_features:
            feats = feats[rng.choice(len(feats), lk.max_features, replace=False)]
        n_feat[k] = len(feats)
        if len(feats) >= cfg.min_features and alpha > 0:
            if np.isfinite(s_slow) and s_fast < rec.inject_ratio * s_slow:
                share = min(rec.max_inject, 1.0 - s_fast / (rec.inject_ratio * s_slow) + 1.0 / cfg.n_particles)
                particles, calib, weights, injected[k] = _inject(particles, calib, weights, share, feats, raster,
                                                                 s_slow, cfg, rng)
                s_fast = s_slow if injected[k] else s_fast
            particles, calib, weights, score_out[k] = _update(particles, calib, weights, feats, raster, alpha, cfg, lk,
                                                                   rng)
            if np.isfinite(score_out[k]):
                s_slow = score_out[k] if np.isnan(s_slow) else s_slow + rec.score_slow * (score_out[k] - s_slow)
                s_fast = score_out[k] if np.isnan(s_fast) else s_fast + rec.score_fast * (score_out[k] - s_fast)
            travel = 0.0
            ess_out[k] = mcl.effective_sample_size(weights)
            if ess_out[k] < cfg.resample_neff_ratio * cfg.n_particles:
                particles, calib, weights = _resample(particles, calib, weights, cfg, rng)
        q_out[k], P_out[k] = mcl.estimate(particles, weights)
        cal_out[k] = weights @ calib
    q_out[:, 2] = np.where(np.isfinite(q_out[:, 2]), wrap_angle_rad(q_out[:, 2]), np.nan)
    return MclRun(q_out, P_out, n_feat, cal_out, ess_out, score_out, injected)
