"""The base graph of a set of drives: odometry factors, GNSS position factors with their bias chain, INS attitude
priors (pass 1 of the pose graph, before loops and anchors)."""
from __future__ import annotations

import numpy as np

from stages.posegraph.factors.drive import DriveInput, initial_poses
from stages.posegraph.factors.gnss import attitude_priors, gnss_position_priors
from stages.posegraph.factors.graph import PosePrior, Problem
from stages.posegraph.factors.odometry import odometry_betweens, span_betweens
from stages.posegraph.factors.wheel import WheelNoise


def wheel_noise_from_params(p) -> WheelNoise | None:
    if not p.wheel_bridges:
        return None
    return WheelNoise(p.wheel_sigma_m, p.wheel_scale_sigma, p.wheel_sigma_rad, p.wheel_height_sigma_m,
                      p.wheel_tilt_sigma_rad)


def wheel_fusion_noise_from_params(p) -> WheelNoise | None:
    if not p.wheel_fusion:
        return None
    return WheelNoise(p.wheel_fusion_sigma_m, p.wheel_fusion_scale_sigma, p.wheel_fusion_sigma_rad,
                      p.wheel_height_sigma_m, p.wheel_tilt_sigma_rad)


def base_problem(drives: list[DriveInput], p) -> tuple[Problem, np.ndarray]:
    """Odometry + bridges + GNSS + attitude for all drives in one graph; returns it and the drive offsets."""
    offsets = np.cumsum([0] + [d.n for d in drives])
    initial = np.concatenate([initial_poses(d) for d in drives]) if drives else np.zeros((0, 4, 4))
    problem = Problem(int(offsets[-1]), initial)
    for d, off in zip(drives, offsets):
        idx = off + np.arange(d.n)
        problem.betweens += odometry_betweens(d, int(off), p.failed_edge_sigma_m, p.failed_edge_sigma_rad,
                                              wheel_noise_from_params(p), wheel_fusion_noise_from_params(p))
        if p.span_edges:
            problem.betweens += span_betweens(d, int(off), p.span_edge_kernel, p.span_edge_kernel_k)
        gnss = gnss_position_priors(
            idx, d.stamps_ns, d.gnss_T, d.gnss_std_enu_m, d.gnss_valid, every_s=p.gnss_every_s,
            inflation=p.gnss_std_inflation, min_std_m=p.gnss_min_std_m, robust=p.gnss_kernel,
            kernel_k=p.gnss_kernel_k, lever_arm_m=np.asarray(p.gnss_lever_arm_m), bias_tau_s=p.gnss_bias_tau_s,
            white_sigma_m=p.gnss_white_sigma_m, bias_offset=problem.n_biases)
        problem.positions += gnss.positions
        problem.bias_links += gnss.bias_links
        problem.bias_priors += gnss.bias_priors
        problem.n_biases += gnss.n_biases
        problem.attitudes += attitude_priors(
            idx, d.stamps_ns, d.gnss_T, d.gnss_std_yaw_rad, d.gnss_valid, every_s=p.gnss_every_s,
            roll_pitch_sigma_rad=p.attitude_sigma_rad, yaw_inflation=p.heading_std_inflation,
            with_yaw=p.heading_prior, roll_pitch_known=d.gnss_roll_pitch_known,
            unknown_roll_pitch_sigma_rad=p.unknown_roll_pitch_sigma_rad)
        if not d.gnss_valid.any():  # no GNSS at all: hold the drive's first pose (loops may still move it)
            problem.pose_priors.append(PosePrior(int(off), initial[off], np.eye(6) * 1e-2, "fixed"))
    return problem, offsets
