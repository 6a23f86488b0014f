"""The base graph of a set of drives: odometry factors, GNSS position factors with their bias chain, INS attitude
priors, and for a drive without GNSS its prior trajectory and start pose (``factors.prior``) (pass 1 of the pose
graph, before loops and anchors)."""
from __future__ import annotations

import numpy as np

from stages.posegraph.config import FactorConfig, GnssConfig, PriorConfig
from stages.posegraph.factors.drive import DriveInput, initial_poses
from stages.posegraph.factors.gnss import attitude_priors, gnss_position_priors
from stages.posegraph.factors.graph import PosePrior, Problem
from stages.posegraph.factors.odometry import odometry_betweens, span_betweens
from stages.posegraph.factors.prior import prior_factors


def base_problem(drives: list[DriveInput], factors: FactorConfig, gnss_cfg: GnssConfig,
                 prior_cfg: PriorConfig | None = None) -> tuple[Problem, np.ndarray]:
    """Odometry + bridges + GNSS + attitude for all drives in one graph, and the prior trajectory and start pose of
    a drive without GNSS (``prior_cfg``; None: the defaults); returns it and the drive offsets."""
    prior_cfg = prior_cfg or PriorConfig(unknown_roll_pitch_sigma_rad=gnss_cfg.unknown_roll_pitch_sigma_rad)
    offsets = np.cumsum([0] + [d.n for d in drives])
    initial = np.concatenate([initial_poses(d) for d in drives]) if drives else np.zeros((0, 4, 4))
    problem = Problem(int(offsets[-1]), initial)
    for d, off in zip(drives, offsets):
        idx = off + np.arange(d.n)
        problem.betweens += odometry_betweens(d, int(off), factors)
        if factors.span_edges:
            problem.betweens += span_betweens(d, int(off), factors)
        gnss = gnss_position_priors(idx, d.stamps_ns, d.gnss_T, d.gnss_std_enu_m, d.gnss_valid, gnss_cfg,
                                    bias_offset=problem.n_biases)
        problem.positions += gnss.positions
        problem.bias_links += gnss.bias_links
        problem.bias_priors += gnss.bias_priors
        problem.n_biases += gnss.n_biases
        problem.attitudes += attitude_priors(idx, d.stamps_ns, d.gnss_T, d.gnss_std_yaw_rad, d.gnss_valid, gnss_cfg,
                                             roll_pitch_known=d.gnss_roll_pitch_known)
        if d.gnss_valid.any():
            continue
        # no GNSS: the prior trajectory and start pose place the drive; with neither, its first pose is held where
        # it starts (loops may still move it)
        priors, shape = prior_factors(d.prior, d.scan_ids, d.stamps_ns, int(off), prior_cfg)
        problem.pose_priors += priors
        problem.betweens += shape
        if not priors:
            problem.pose_priors.append(PosePrior(int(off), initial[off], np.eye(6) * 1e-2, "fixed"))
    return problem, offsets
