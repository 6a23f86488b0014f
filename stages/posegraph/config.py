"""The pose graph's settings in sections, one per part of the algorithm: odometry factors, GNSS/INS priors, loop
closures, survey anchors, the solver. ``PosegraphConfig.from_params`` builds them from the stage's flat params
(the workflow surface) and is the only place that reads those; every function below the stage adapter receives
its section, never the params object. Tests and benches build them the same way or directly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from stages.common.marking_raster.settings import MarkingRasterSettings

if TYPE_CHECKING:
    from stages.posegraph.params import PosegraphParams


@dataclass(frozen=True)
class WheelNoise:
    """Std devs of a wheel-odometry increment (vehicle frame): horizontal ``sigma_m`` plus ``scale_sigma`` of
    the distance along track, heading ``sigma_rad``; a planar increment says little about height, roll and
    pitch (``height_sigma_m``, ``tilt_sigma_rad``)."""

    sigma_m: float
    scale_sigma: float
    sigma_rad: float
    height_sigma_m: float
    tilt_sigma_rad: float


@dataclass(frozen=True)
class RegistrationNoise:
    """Std added (in quadrature) to every ICP registration's own covariance: its along-track, cross-track and yaw
    error beyond what its point-to-plane Hessian states (the Hessian counts every point as independent)."""

    along_m: float
    cross_m: float
    yaw_rad: float


@dataclass(frozen=True)
class FactorConfig:
    """Between factors along a drive: a weak bridge of ``failed_edge_sigma_*`` over a missing or rejected ICP
    edge, the wheel increment as the bridge where the drive has one (``wheel_bridge``) and beside every accepted
    edge (``wheel_fusion``; None: not used), and the odometry's span edges under a robust kernel."""

    failed_edge_sigma_m: float
    failed_edge_sigma_rad: float
    wheel_bridge: WheelNoise | None
    wheel_fusion: WheelNoise | None
    span_edges: bool
    span_edge_kernel: str
    span_edge_kernel_k: float
    registration_sigma: RegistrationNoise | None  # None: the odometry's own information alone

    @property
    def uses_wheel(self) -> bool:
        """Whether any factor needs the drive's wheel odometry."""
        return self.wheel_bridge is not None or self.wheel_fusion is not None


@dataclass(frozen=True)
class GnssConfig:
    """GNSS position factors (one per ``every_s``, reported std x ``std_inflation`` floored at ``min_std_m``,
    robust kernel, a Gauss-Markov bias of correlation time ``bias_tau_s``) and INS attitude priors on the same
    epochs (roll/pitch; yaw only with ``heading_prior``)."""

    every_s: float
    std_inflation: float
    min_std_m: float
    kernel: str
    kernel_k: float
    lever_arm_m: tuple[float, float, float]
    bias_tau_s: float
    white_sigma_m: float
    attitude_sigma_rad: float
    unknown_roll_pitch_sigma_rad: float
    heading_prior: bool
    heading_std_inflation: float


@dataclass(frozen=True)
class LoopVerifyConfig:
    """The ICP verification of one loop candidate (``loops.verify.verify_loop``): coarse-to-fine GICP stages,
    the alignment score's search radius and plane tolerance, and the acceptance gates."""

    voxel_m: float
    max_corr_m: float
    min_fitness: float
    max_rmse_m: float
    max_correction_m: float
    max_correction_rad: float
    consistency_m: float
    min_sigma_m: float
    min_sigma_rad: float
    coarse_voxel_m: float = 1.0
    coarse_corr_m: float = 3.0
    inlier_m: float = 1.0
    plane_tol_m: float = 0.1
    relative_tolerance: float = 1e-4  # each GICP stage's convergence criterion (open3d's relative fitness and RMSE)
    ground_split: bool = False  # an accepted loop refined on the structure, height/roll/pitch from the road planes
    ground_split_max_shift_m: float = 0.3  # the refinement replaces the loop when it moves it less (``verify_loop``)
    ground_tolerance_m: float = 0.25  # points this near a scan's road plane are road (the odometry's default)


class _Parallel:
    """A step whose independent items run in parallel processes from ``parallel_min_items`` on."""

    parallel_min_items: int

    def workers(self, n_items: int) -> int | None:
        """All the machine's processes (None) from ``parallel_min_items`` independent items on, else this one."""
        return None if n_items >= self.parallel_min_items else 1


@dataclass(frozen=True)
class LoopConfig(_Parallel):
    """Loop closures: candidates (one query per ``stride_m`` of travel, a reference drive's onto the map one per
    ``reference_stride_m``, other passes within ``radius_m``), their
    verification, the kernel of the accepted loops and the pass-3 gate; candidates run in parallel processes
    from ``parallel_min_items`` on. With survey anchors, only query poses that the anchors within ``survey_window_m``
    of travel hold to less than ``survey_sigma_m`` in one direction or none look for loops (window 0: all)."""

    radius_m: float
    min_separation_s: float
    stride_m: float
    max_per_scan: int
    verify: LoopVerifyConfig
    survey_window_m: float
    survey_sigma_m: float
    kernel: str
    kernel_k: float
    max_whitened_residual: float
    parallel_min_items: int
    reference_stride_m: float  # a reference drive's loop queries onto the fixed map, one per this travel
    incremental_max_per_scan: int = 1  # incremental solve: loop targets per query scan of a new drive
    # the wide search where nothing absolute holds a drive (``loops/wide.py``)
    wide: bool = True
    wide_sigmas: float = 3.0  # Mahalanobis gate of the estimated offset less radius_m
    wide_min_sigma_m: float = 3.0  # only where the relative position's std exceeds this
    wide_stride_m: float = 15.0  # one wide query per this much travel
    wide_max_per_scan: int = 4
    wide_target_spacing_m: float = 8.0  # a query's wide targets at least this far apart along their pass
    wide_rounds: int = 3
    wide_global_voxel_m: float = 1.0  # FPFH + RANSAC voxel
    wide_yaw_slack_deg: float = 5.0  # added in quadrature to the chain's heading std in the global match's gate
    wide_min_consistent: int = 2  # a consistent set smaller than this is not accepted
    pcm_probability: float = 0.99  # chi-square gate (3 dof) of a loop pair's cycle
    pcm_window_m: float = 100.0  # pairs checked only when both odometry segments are shorter (travel)


@dataclass(frozen=True)
class GroundAnchorConfig:
    """The vertical survey anchor of one keyframe (``anchors.survey_anchor.anchor_scan``): GICP of its points below
    ``max_height_m`` onto the survey cropped to ``crop_m``, both at ``voxel_m``, and its gates."""

    crop_m: float
    max_height_m: float
    voxel_m: float
    min_fitness: float
    max_rmse_m: float
    min_sigma_m: float
    min_sigma_rad: float
    vertical_only: bool = True


@dataclass(frozen=True)
class MarkingAnchorConfig:
    """The horizontal survey anchor of one keyframe (``anchors.survey_markings.marking_anchor``): its marking
    submap, the search, the anchor std from the peak's width, the heading search, the survey's raster."""

    half_travel_m: float
    max_scans: int
    search_m: float
    raster: MarkingRasterSettings
    sigma_scale: float = 1.0
    min_sigma_m: float = 0.03
    yaw_search_deg: float = 0.0
    yaw_step_deg: float = 0.5
    scan_step: int = 1  # every scan_step-th scan of the submap's window (``submap_scan_indices``)


@dataclass(frozen=True)
class AnchorConfig(_Parallel):
    """Survey anchors: one keyframe per ``stride_m``, its ground registration, its marking match (when
    ``use_markings``; heading prior of ``yaw_sigma_deg``, 0: none), the consensus check of the horizontal anchors,
    keyframes matched in blocks of ``block``, in parallel processes from ``parallel_min_items`` on; matched again
    from the anchored estimate (at most ``rounds`` in all) while a round moves a pose more than ``round_tol_*``."""

    stride_m: float
    ground: GroundAnchorConfig
    use_markings: bool
    markings: MarkingAnchorConfig
    yaw_sigma_deg: float
    consensus_window_m: float
    consensus_drift_sigma_m: float
    consensus_probability: float
    block: int
    parallel_min_items: int
    rounds: int
    round_tol_m: float
    round_tol_deg: float


@dataclass(frozen=True)
class PriorConfig:
    """A drive without GNSS: its prior trajectory and start pose as factors (``factors/prior.py``)."""

    every_s: float  # one absolute prior / shape factor per this many seconds (0: every scan)
    kernel: str  # huber | cauchy | none, on the prior trajectory's factors (not the start's)
    kernel_k: float
    unknown_roll_pitch_sigma_rad: float  # roll / pitch the prior leaves unknown (NaN std)


@dataclass(frozen=True)
class SolveConfig:
    """Levenberg-Marquardt stopping rules, the tight prior on map poses held fixed for a reference drive,
    whether the marginal covariances are computed, and how many pose pairs per distance bin give the map's
    error-correlation kernel (0: none; ``error_correlation.py``)."""

    max_iterations: int
    lm_relative_error_tol: float
    fixed_prior_sigma_m: float
    compute_marginals: bool
    error_kernel_pairs_per_bin: int

    def lm_kwargs(self) -> dict:
        """The keywords of ``factors.graph.optimize``."""
        return {"max_iterations": self.max_iterations, "relative_error_tol": self.lm_relative_error_tol}


@dataclass(frozen=True)
class RegionConfig:
    """The region-wise solve (``regions.py``; ``cornermap maps reoptimize``): most poses of a region (0: one joint
    solve), most separator updates, the separator move that ends it (m; a tenth of it in rad)."""

    max_poses: int = 0
    rounds: int = 20
    tol_m: float = 1e-4


@dataclass(frozen=True)
class PosegraphConfig:
    factors: FactorConfig
    gnss: GnssConfig
    loops: LoopConfig
    anchors: AnchorConfig
    solve: SolveConfig
    prior: PriorConfig
    regions: RegionConfig = RegionConfig()

    @classmethod
    def from_params(cls, p: PosegraphParams) -> PosegraphConfig:
        """The sections from the stage's flat params (the workflow's ``params.posegraph`` keys)."""
        wheel_bridge = WheelNoise(p.wheel_sigma_m, p.wheel_scale_sigma, p.wheel_sigma_rad, p.wheel_height_sigma_m,
                                  p.wheel_tilt_sigma_rad) if p.wheel_bridges else None
        wheel_fusion = WheelNoise(p.wheel_fusion_sigma_m, p.wheel_fusion_scale_sigma, p.wheel_fusion_sigma_rad,
                                  p.wheel_height_sigma_m, p.wheel_tilt_sigma_rad) if p.wheel_fusion else None
        factors = FactorConfig(
            failed_edge_sigma_m=p.failed_edge_sigma_m, failed_edge_sigma_rad=p.failed_edge_sigma_rad,
            wheel_bridge=wheel_bridge, wheel_fusion=wheel_fusion, span_edges=p.span_edges,
            span_edge_kernel=p.span_edge_kernel, span_edge_kernel_k=p.span_edge_kernel_k,
            registration_sigma=RegistrationNoise(p.icp_edge_sigma_along_m, p.icp_edge_sigma_cross_m,
                                                 math.radians(p.icp_edge_sigma_yaw_deg)))
        gnss = GnssConfig(
            every_s=p.gnss_every_s, std_inflation=p.gnss_std_inflation, min_std_m=p.gnss_min_std_m,
            kernel=p.gnss_kernel, kernel_k=p.gnss_kernel_k, lever_arm_m=tuple(p.gnss_lever_arm_m),
            bias_tau_s=p.gnss_bias_tau_s, white_sigma_m=p.gnss_white_sigma_m, attitude_sigma_rad=p.attitude_sigma_rad,
            unknown_roll_pitch_sigma_rad=p.unknown_roll_pitch_sigma_rad, heading_prior=p.heading_prior,
            heading_std_inflation=p.heading_std_inflation)
        verify = LoopVerifyConfig(
            voxel_m=p.loop_voxel_m, max_corr_m=p.loop_max_corr_m, min_fitness=p.loop_min_fitness,
            max_rmse_m=p.loop_max_rmse_m, max_correction_m=p.loop_max_correction_m,
            max_correction_rad=p.loop_max_correction_rad, consistency_m=p.loop_consistency_m,
            min_sigma_m=p.loop_min_sigma_m, min_sigma_rad=p.loop_min_sigma_rad, coarse_voxel_m=p.loop_coarse_voxel_m,
            coarse_corr_m=p.loop_coarse_corr_m, inlier_m=p.loop_inlier_m, plane_tol_m=p.loop_plane_tol_m,
            relative_tolerance=p.loop_relative_tolerance, ground_split=p.loop_ground_split)
        loops = LoopConfig(
            radius_m=p.loop_radius_m, min_separation_s=p.loop_min_separation_s, stride_m=p.loop_stride_m,
            max_per_scan=p.loop_max_per_scan, verify=verify, survey_window_m=p.loop_survey_window_m,
            survey_sigma_m=p.loop_survey_sigma_m, kernel=p.loop_kernel, kernel_k=p.loop_kernel_k,
            max_whitened_residual=p.loop_max_whitened_residual, parallel_min_items=p.parallel_min_items,
            reference_stride_m=p.loop_reference_stride_m, incremental_max_per_scan=p.loop_incremental_max_per_scan,
            wide=p.loop_wide, wide_sigmas=p.loop_wide_sigmas, wide_min_sigma_m=p.loop_wide_min_sigma_m,
            wide_stride_m=p.loop_wide_stride_m, wide_max_per_scan=p.loop_wide_max_per_scan,
            wide_target_spacing_m=p.loop_wide_target_spacing_m, wide_rounds=p.loop_wide_rounds,
            wide_global_voxel_m=p.loop_wide_global_voxel_m, wide_yaw_slack_deg=p.loop_wide_yaw_slack_deg,
            wide_min_consistent=p.loop_wide_min_consistent, pcm_probability=p.loop_pcm_probability,
            pcm_window_m=p.loop_pcm_window_m)
        ground = GroundAnchorConfig(
            crop_m=p.survey_crop_m, max_height_m=p.survey_max_height_m, voxel_m=p.loop_voxel_m / 2,
            min_fitness=p.survey_min_fitness, max_rmse_m=p.survey_max_rmse_m, min_sigma_m=p.survey_min_sigma_m,
            min_sigma_rad=p.survey_min_sigma_rad, vertical_only=p.survey_vertical_only)
        markings = MarkingAnchorConfig(
            half_travel_m=p.survey_marking_half_travel_m, max_scans=p.survey_marking_max_scans,
            search_m=p.survey_marking_search_m, raster=p.survey_marking_raster,
            sigma_scale=p.survey_marking_sigma_scale, min_sigma_m=p.survey_marking_min_sigma_m,
            yaw_search_deg=p.survey_marking_yaw_search_deg, yaw_step_deg=p.survey_marking_yaw_step_deg,
            scan_step=p.survey_marking_scan_step)
        anchors = AnchorConfig(
            stride_m=p.survey_stride_m, ground=ground, use_markings=p.survey_markings, markings=markings,
            yaw_sigma_deg=p.survey_marking_yaw_sigma_deg, consensus_window_m=p.survey_marking_consensus_window_m,
            consensus_drift_sigma_m=p.survey_marking_consensus_drift_sigma_m,
            consensus_probability=p.survey_marking_consensus_probability, block=p.survey_marking_block,
            parallel_min_items=p.parallel_min_items, rounds=p.survey_rounds, round_tol_m=p.survey_round_tol_m,
            round_tol_deg=p.survey_round_tol_deg)
        solve = SolveConfig(max_iterations=p.max_iterations, lm_relative_error_tol=p.lm_relative_error_tol,
                            fixed_prior_sigma_m=p.fixed_prior_sigma_m, compute_marginals=p.compute_marginals,
                            error_kernel_pairs_per_bin=p.error_kernel_pairs_per_bin)
        prior = PriorConfig(every_s=p.prior_every_s, kernel=p.prior_kernel, kernel_k=p.prior_kernel_k,
                            unknown_roll_pitch_sigma_rad=p.unknown_roll_pitch_sigma_rad)
        regions = RegionConfig(p.region_max_poses, p.region_rounds, p.region_tol_m)
        return cls(factors, gnss, loops, anchors, solve, prior, regions)
