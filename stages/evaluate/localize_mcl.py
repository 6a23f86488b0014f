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

log = logging.getLogger(__name__)

RasterFetcher = Callable[[float, float, float, float], mcl.Raster]


@dataclass(frozen=True)
class MclConfig:
    n_particles: int = 1000
    init_sigma_xy_m: float = 1.0
    init_sigma_yaw_rad: float = np.deg2rad(1.0)
    sigma_frac: float = 0.03  # translation noise per metre travelled
    sigma_xy_m: float = 0.02  # translation noise floor per step
    sigma_yaw_rad: float = np.deg2rad(0.1)  # heading noise per step
    sharpness: float = 8.0  # log-likelihood gain per effective feature point at full correlation
    effective_points: float = 60.0
    max_features: int = 400
    resample_neff_ratio: float = 0.5
    window_m: float = 240.0  # side of a fetched raster window
    feature_range_m: float = 30.0
    min_features: int = 10


@dataclass(frozen=True)
class MclRun:
    q: np.ndarray  # (E,3), NaN before initialisation
    P: np.ndarray  # (E,3,3)
    n_features: np.ndarray  # (E,) int


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


def run_mcl(increments: np.ndarray, feature_epoch: np.ndarray, features_vehicle_m: np.ndarray,
            fetch: RasterFetcher, q0: np.ndarray, start_epoch: int, rng: np.random.Generator,
            cfg: MclConfig = MclConfig()) -> MclRun:
    """Run the particle filter from ``start_epoch`` (particles drawn about q0) to the last epoch."""
    n = len(increments)
    q_out = np.full((n, 3), np.nan)
    P_out = np.full((n, 3, 3), np.nan)
    n_feat = np.zeros(n, dtype=np.int32)
    off = np.searchsorted(feature_epoch, np.arange(n + 1))
    particles = mcl.init_particles(q0, cfg.init_sigma_xy_m, cfg.init_sigma_yaw_rad, cfg.n_particles, rng)
    weights = np.full(cfg.n_particles, 1.0 / cfg.n_particles)
    raster = _window_around(q0, fetch, cfg)
    margin = cfg.feature_range_m + 3.0 * cfg.init_sigma_xy_m
    for k in range(start_epoch, n):
        if k > start_epoch:
            particles = mcl.predict_particles(particles, increments[k], cfg.sigma_frac, cfg.sigma_xy_m,
                                              cfg.sigma_yaw_rad, rng)
        feats = features_vehicle_m[off[k]:off[k + 1]]
        if len(feats) > cfg.max_features:
            feats = feats[rng.choice(len(feats), cfg.max_features, replace=False)]
        n_feat[k] = len(feats)
        if len(feats) >= cfg.min_features:
            lo, hi = particles[:, :2].min(axis=0) - margin, particles[:, :2].max(axis=0) + margin
            if not raster.contains(lo[0], lo[1], hi[0], hi[1]):
                raster = _window_around(np.average(particles, axis=0, weights=weights), fetch, cfg)
            scores = mcl.correlation_scores(particles, feats, raster)
            logw = np.log(weights) + mcl.log_likelihood(scores, len(feats), cfg.sharpness, cfg.effective_points)
            weights = np.exp(logw - logw.max())
            weights /= weights.sum()
            if mcl.effective_sample_size(weights) < cfg.resample_neff_ratio * cfg.n_particles:
                particles = particles[mcl.low_variance_resample(weights, rng)]
                weights = np.full(cfg.n_particles, 1.0 / cfg.n_particles)
        q_out[k], P_out[k] = mcl.estimate(particles, weights)
    q_out[:, 2] = np.where(np.isfinite(q_out[:, 2]), wrap_angle_rad(q_out[:, 2]), np.nan)
    return MclRun(q_out, P_out, n_feat)
