"""The base graph of a set of drives: odometry factors, GNSS position factors with their bias chain, INS attitude
priors (pass 1 of the pose graph, before loops and anchors)."""
from __future__ import annotations

import numpy as np

from stages.posegraph.config import FactorConfig, GnssConfig
from stages.posegraph.factors.drive import DriveInput, initial_poses
from stages.posegraph.factors.gnss import attitude_priors, gnss_position_priors
from stages.posegraph.factors.graph import PosePrior, Problem
from stages.posegraph.factors.odometry import odometry_betweens, span_betweens


def base_problem(drives: list[DriveInput], factors: FactorConfig, gnss_cfg: GnssConfig) -> tuple[Problem, np.ndarray]:
    """Odometry + bridges + GNSS + attitude for all drives in one graph; returns it and the drive offsets."""
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
        if not d.gnss_valid.any():  # no GNSS at all: hold the drive's first pose (loops may still move it)
            problem.pose_priors.append(PosePrior(int(off), initial[off], np.eye(6) * 1e-2, "fixed"))
    return problem, offsets
