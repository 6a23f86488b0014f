"""Parameters of the posegraph stage: the algorithm's config sections (config.py) nested as the workflow's
``params.posegraph`` keys, e.g. ``{loops: {radius_m: 12.0, wide: {enabled: false}}, anchors: {markings: {...}}}``.
Defaults measured on simulated drives, see docs/posegraph.md."""
from __future__ import annotations

from typing import ClassVar, Mapping

from pydantic import Field

from pipeline.declare import Params
from stages.posegraph.config import (
    AnchorConfig,
    FactorConfig,
    GnssConfig,
    LoopConfig,
    PriorConfig,
    RegionConfig,
    SolveConfig,
)


class PosegraphParams(Params):
    """The pose graph's settings, one section per part of the algorithm; each function below the stage adapter
    receives its section."""

    factors: FactorConfig = Field(default_factory=FactorConfig, description="odometry, wheel and span edges")
    gnss: GnssConfig = Field(default_factory=GnssConfig, description="GNSS position factors and INS attitude priors")
    prior: PriorConfig = Field(default_factory=PriorConfig, description="a GNSS-free drive's prior trajectory")
    loops: LoopConfig = Field(default_factory=LoopConfig, description="loop closures")
    anchors: AnchorConfig = Field(default_factory=AnchorConfig, description="survey anchors")
    solve: SolveConfig = Field(default_factory=SolveConfig, description="the solver and its outputs")
    regions: RegionConfig = Field(default_factory=RegionConfig, description="the region-wise solve")

    # the flat keys of before the sections -> their place now (refused with it)
    renamed: ClassVar[Mapping[str, str]] = {
        "failed_edge_sigma_m": "factors.failed_edge_sigma_m",
        "failed_edge_sigma_rad": "factors.failed_edge_sigma_rad",
        "wheel_bridges": "factors.wheel.bridges",
        "wheel_sigma_m": "factors.wheel.sigma_m",
        "wheel_scale_sigma": "factors.wheel.scale_sigma",
        "wheel_sigma_rad": "factors.wheel.sigma_rad",
        "wheel_height_sigma_m": "factors.wheel.height_sigma_m",
        "wheel_tilt_sigma_rad": "factors.wheel.tilt_sigma_rad",
        "wheel_fusion": "factors.wheel.fusion",
        "wheel_fusion_sigma_m": "factors.wheel.fusion_sigma_m",
        "wheel_fusion_scale_sigma": "factors.wheel.fusion_scale_sigma",
        "wheel_fusion_sigma_rad": "factors.wheel.fusion_sigma_rad",
        "icp_edge_sigma_along_m": "factors.registration.along_m",
        "icp_edge_sigma_cross_m": "factors.registration.cross_m",
        "icp_edge_sigma_yaw_deg": "factors.registration.yaw_deg",
        "span_edges": "factors.span_edges",
        "span_edge_kernel": "factors.span_edge_kernel",
        "span_edge_kernel_k": "factors.span_edge_kernel_k",
        "gnss_std_inflation": "gnss.std_inflation",
        "gnss_min_std_m": "gnss.min_std_m",
        "gnss_every_s": "gnss.every_s",
        "gnss_bias_tau_s": "gnss.bias_tau_s",
        "gnss_white_sigma_m": "gnss.white_sigma_m",
        "gnss_kernel": "gnss.kernel",
        "gnss_kernel_k": "gnss.kernel_k",
        "gnss_lever_arm_m": "gnss.lever_arm_m",
        "attitude_sigma_rad": "gnss.attitude_sigma_rad",
        "unknown_roll_pitch_sigma_rad": "gnss.unknown_roll_pitch_sigma_rad (and prior.unknown_roll_pitch_sigma_rad)",
        "heading_prior": "gnss.heading_prior",
        "heading_std_inflation": "gnss.heading_std_inflation",
        "prior_every_s": "prior.every_s",
        "prior_kernel": "prior.kernel",
        "prior_kernel_k": "prior.kernel_k",
        "loop_radius_m": "loops.radius_m",
        "loop_min_separation_s": "loops.min_separation_s",
        "loop_stride_m": "loops.stride_m",
        "loop_max_per_scan": "loops.max_per_scan",
        "loop_reference_stride_m": "loops.reference_stride_m",
        "loop_incremental_max_per_scan": "loops.incremental_max_per_scan",
        "loop_survey_window_m": "loops.survey_window_m",
        "loop_survey_sigma_m": "loops.survey_sigma_m",
        "loop_wide": "loops.wide.enabled",
        "loop_wide_sigmas": "loops.wide.sigmas",
        "loop_wide_min_sigma_m": "loops.wide.min_sigma_m",
        "loop_wide_stride_m": "loops.wide.stride_m",
        "loop_wide_max_per_scan": "loops.wide.max_per_scan",
        "loop_wide_target_spacing_m": "loops.wide.target_spacing_m",
        "loop_wide_rounds": "loops.wide.rounds",
        "loop_wide_global_voxel_m": "loops.wide.global_voxel_m",
        "loop_wide_yaw_slack_deg": "loops.wide.yaw_slack_deg",
        "loop_wide_min_consistent": "loops.wide.min_consistent",
        "loop_pcm_probability": "loops.pcm_probability",
        "loop_pcm_window_m": "loops.pcm_window_m",
        "loop_kernel": "loops.kernel",
        "loop_kernel_k": "loops.kernel_k",
        "loop_max_whitened_residual": "loops.max_whitened_residual",
        "loop_coarse_voxel_m": "loops.verify.coarse_voxel_m",
        "loop_coarse_corr_m": "loops.verify.coarse_corr_m",
        "loop_voxel_m": "loops.verify.voxel_m (the survey ground anchor's voxel: anchors.ground.voxel_m)",
        "loop_max_corr_m": "loops.verify.max_corr_m",
        "loop_relative_tolerance": "loops.verify.relative_tolerance",
        "loop_ground_split": "loops.verify.ground_split",
        "loop_inlier_m": "loops.verify.inlier_m",
        "loop_plane_tol_m": "loops.verify.plane_tol_m",
        "loop_min_fitness": "loops.verify.min_fitness",
        "loop_max_rmse_m": "loops.verify.max_rmse_m",
        "loop_max_correction_m": "loops.verify.max_correction_m",
        "loop_max_correction_rad": "loops.verify.max_correction_rad",
        "loop_consistency_m": "loops.verify.consistency_m",
        "loop_min_sigma_m": "loops.verify.min_sigma_m",
        "loop_min_sigma_rad": "loops.verify.min_sigma_rad",
        "parallel_min_items": "loops.parallel_min_items (and anchors.parallel_min_items)",
        "survey_stride_m": "anchors.stride_m",
        "survey_crop_m": "anchors.ground.crop_m",
        "survey_max_height_m": "anchors.ground.max_height_m",
        "survey_min_fitness": "anchors.ground.min_fitness",
        "survey_max_rmse_m": "anchors.ground.max_rmse_m",
        "survey_min_sigma_m": "anchors.ground.min_sigma_m",
        "survey_min_sigma_rad": "anchors.ground.min_sigma_rad",
        "survey_vertical_only": "anchors.ground.vertical_only",
        "survey_markings": "anchors.use_markings",
        "survey_marking_half_travel_m": "anchors.markings.half_travel_m",
        "survey_marking_max_scans": "anchors.markings.max_scans",
        "survey_marking_scan_step": "anchors.markings.scan_step",
        "survey_marking_search_m": "anchors.markings.search_m",
        "survey_marking_sigma_scale": "anchors.markings.sigma_scale",
        "survey_marking_min_sigma_m": "anchors.markings.min_sigma_m",
        "survey_marking_yaw_search_deg": "anchors.markings.yaw_search_deg",
        "survey_marking_yaw_step_deg": "anchors.markings.yaw_step_deg",
        "survey_marking_raster": "anchors.markings.raster",
        "survey_marking_yaw_sigma_deg": "anchors.yaw_sigma_deg",
        "survey_marking_consensus_window_m": "anchors.consensus_window_m",
        "survey_marking_consensus_drift_sigma_m": "anchors.consensus_drift_sigma_m",
        "survey_marking_consensus_probability": "anchors.consensus_probability",
        "survey_marking_block": "anchors.block",
        "survey_rounds": "anchors.rounds",
        "survey_round_tol_m": "anchors.round_tol_m",
        "survey_round_tol_deg": "anchors.round_tol_deg",
        "max_iterations": "solve.max_iterations",
        "lm_relative_error_tol": "solve.lm_relative_error_tol",
        "fixed_prior_sigma_m": "solve.fixed_prior_sigma_m",
        "compute_marginals": "solve.compute_marginals",
        "error_kernel_pairs_per_bin": "solve.error_kernel_pairs_per_bin",
        "region_max_poses": "regions.max_poses",
        "region_rounds": "regions.rounds",
        "region_tol_m": "regions.tol_m",
    }
