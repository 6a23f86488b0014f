"""GNSS position factors and INS attitude priors from per-scan GNSS/INS poses.

Receivers understate their error in street canyons, so the reported std is inflated and the factor gets a
robust kernel. Consecutive fixes share a slowly varying bias (metres between tall buildings, correlated over
a minute or more). Two models:
- ``bias_tau_s > 0`` (default): each selected fix measures the antenna position plus a bias state; the bias
  states form the exact first-order Gauss-Markov chain (b_n = exp(-dt/tau) b_{n-1} + w, the first state with
  the stationary variance). The trajectory's shape then comes from
  ICP and loops, and GNSS pins only the frame: treating the bias as white noise bends the map along it
  (measured in docs/posegraph.md).
- ``bias_tau_s == 0``: white noise, one factor per ``every_s`` seconds (the earlier model).
Outages (``valid`` false) have no factor.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.posegraph.config import GnssConfig
from stages.posegraph.factors.graph import AttitudePrior, BiasLink, BiasPrior, PositionPrior


def select_epochs(stamps_ns: np.ndarray, valid: np.ndarray, every_s: float) -> np.ndarray:
    """Indices of valid epochs, at most one per ``every_s`` seconds (0: every valid epoch)."""
    idx = np.flatnonzero(valid)
    if every_s <= 0 or len(idx) == 0:
        return idx
    keep, last_ns = [], None
    gap_ns = every_s * 1e9
    for k, t in zip(idx, stamps_ns[idx]):  # per epoch (not per point): greedy, >= every_s apart
        if last_ns is None or t - last_ns >= gap_ns:
            keep.append(k)
            last_ns = t
    return np.asarray(keep, dtype=np.int64)


@dataclass
class GnssFactors:
    positions: list[PositionPrior] = field(default_factory=list)
    bias_links: list[BiasLink] = field(default_factory=list)
    bias_priors: list[BiasPrior] = field(default_factory=list)
    n_biases: int = 0


def gnss_position_priors(pose_index: np.ndarray, stamps_ns: np.ndarray, T_map_vehicle: np.ndarray,
                         std_enu_m: np.ndarray, valid: np.ndarray, cfg: GnssConfig, *,
                         bias_offset: int = 0) -> GnssFactors:
    """One robust position factor per selected epoch (the measured point is the antenna position), with a
    Gauss-Markov bias chain when ``cfg.bias_tau_s`` > 0. The bias std per axis is the inflated reported std;
    bias state indices start at ``bias_offset`` (one chain per drive)."""
    lever = np.asarray(cfg.lever_arm_m, dtype=float)
    inflation, min_std_m, robust, kernel_k = cfg.std_inflation, cfg.min_std_m, cfg.kernel, cfg.kernel_k
    bias_tau_s, white_sigma_m = cfg.bias_tau_s, cfg.white_sigma_m
    out = GnssFactors()
    epochs = select_epochs(stamps_ns, valid, cfg.every_s)
    for n, k in enumerate(epochs):
        T = T_map_vehicle[k]
        antenna = T[:3, 3] + T[:3, :3] @ lever
        if not np.all(np.isfinite(std_enu_m[k])) or not np.all(np.isfinite(antenna)):
            raise ValueError(f"pose {int(pose_index[k])}: GNSS position or std is not finite (std {std_enu_m[k]}); "
                             f"a NaN must never reach a factor: re-run ingest, which applies its std defaults")
        sigma = np.maximum(np.asarray(std_enu_m[k], float) * inflation, min_std_m)
        if bias_tau_s <= 0:
            out.positions.append(PositionPrior(int(pose_index[k]), antenna, sigma, robust, kernel_k, lever))
            continue
        j = bias_offset + n
        out.positions.append(PositionPrior(int(pose_index[k]), antenna, np.full(3, white_sigma_m), robust, kernel_k,
                                           lever, bias=j))
        if n == 0:  # stationary process: the first state has the full variance
            out.bias_priors.append(BiasPrior(j, sigma))
        else:
            dt_s = max((stamps_ns[k] - stamps_ns[epochs[n - 1]]) * 1e-9, 1e-3)
            decay = float(np.exp(-dt_s / bias_tau_s))
            out.bias_links.append(BiasLink(j - 1, j, sigma * np.sqrt(1.0 - decay ** 2), decay))
    out.n_biases = len(epochs) if bias_tau_s > 0 else 0
    return out


def attitude_priors(pose_index: np.ndarray, stamps_ns: np.ndarray, T_map_vehicle: np.ndarray,
                    std_yaw_rad: np.ndarray, valid: np.ndarray, cfg: GnssConfig, *,
                    roll_pitch_known: np.ndarray | None = None) -> list[AttitudePrior]:
    """INS roll/pitch (gravity) as a firm prior (``cfg.attitude_sigma_rad``) and, if ``cfg.heading_prior``, INS
    yaw as a weak one; same epochs as the GNSS factors. An INS heading error is a slowly varying bias like the
    GNSS one: epoch after epoch of independent yaw priors average it into the map (docs/posegraph.md), hence
    optional.

    Where ``roll_pitch_known`` is false (a GNSS without roll/pitch, whose attitude holds yaw only) the stored
    roll/pitch of 0 is not a measurement: the prior on them is ``cfg.unknown_roll_pitch_sigma_rad`` (weak: it only
    keeps the graph determined), never the firm INS sigma."""
    roll_pitch_sigma_rad, unknown_roll_pitch_sigma_rad = cfg.attitude_sigma_rad, cfg.unknown_roll_pitch_sigma_rad
    yaw_inflation, with_yaw = cfg.heading_std_inflation, cfg.heading_prior
    out = []
    for k in select_epochs(stamps_ns, valid, cfg.every_s):
        known = roll_pitch_known is None or bool(roll_pitch_known[k])
        sigma_rp = roll_pitch_sigma_rad if known else unknown_roll_pitch_sigma_rad
        sigma_yaw = max(float(std_yaw_rad[k]) * yaw_inflation, roll_pitch_sigma_rad)
        if not np.isfinite(sigma_yaw):
            raise ValueError(f"pose {int(pose_index[k])}: heading std is not finite ({std_yaw_rad[k]!r}); "
                             f"ingest should have applied its default")
        out.append(AttitudePrior(int(pose_index[k]), T_map_vehicle[k][:3, :3].copy(),
                                 np.array([sigma_rp, sigma_rp, sigma_yaw]), with_yaw))
    return out


def gnss_residuals_enu(T_map_vehicle_est: np.ndarray, priors: list[PositionPrior]) -> np.ndarray:
    """(M,3) estimated antenna position minus GNSS measurement, ENU metres, per factor."""
    if not priors:
        return np.zeros((0, 3))
    out = np.empty((len(priors), 3))
    for n, g in enumerate(priors):
        T = T_map_vehicle_est[g.i]
        out[n] = T[:3, 3] + T[:3, :3] @ g.lever_arm_m - g.position_enu_m
    return out
