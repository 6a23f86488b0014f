"""The pose graph's settings in sections, one per part of the algorithm: odometry factors, GNSS/INS priors, a
GNSS-free drive's prior trajectory, loop closures, survey anchors, the solver, the region-wise solve. Each section is
a frozen ``Params`` holding its defaults (written here only); ``PosegraphParams`` (params.py) nests them as the
workflow's ``params.posegraph`` keys (``loops: {radius_m: 12, wide: {enabled: false}}``), and every function below
the stage adapter receives its section. Tests and benches build them the same way (``PosegraphParams(loops={...})``)
or a section directly (``LoopVerifyConfig(voxel_m=0.3)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pydantic import Field

from pipeline.declare import Params
from stages.common.marking_raster.settings import MarkingRasterSettings

Kernel = Literal["huber", "cauchy", "none"]


@dataclass(frozen=True)
class WheelNoise:
    """Std devs of a wheel-odometry increment (vehicle frame): horizontal ``sigma_m`` plus ``scale_sigma`` of
    the distance along track, heading ``sigma_rad``; a planar increment says little about height, roll and
    pitch (``height_sigma_m``, ``tilt_sigma_rad``). Built from ``WheelConfig`` (no defaults of its own)."""

    sigma_m: float
    scale_sigma: float
    sigma_rad: float
    height_sigma_m: float
    tilt_sigma_rad: float


@dataclass(frozen=True)
class RegistrationNoise:
    """Std added (in quadrature) to every ICP registration's own covariance: its along-track, cross-track and yaw
    error beyond what its point-to-plane Hessian states (the Hessian counts every point as independent). Built from
    ``RegistrationSigma`` (no defaults of its own)."""

    along_m: float
    cross_m: float
    yaw_rad: float


class WheelConfig(Params):
    """The wheel-odometry increment as a factor: the bridge over a missing or rejected ICP edge (``bridges``) and
    the fused increment beside every accepted ICP edge (``fusion``), each with its std devs."""

    bridges: bool = Field(True, description="where ICP failed and the drive has wheel odometry, bridge with the "
                          "wheel increment (gangnam: 1.2 % scale error, 0.01 deg yaw per scan) instead of the GNSS/INS "
                          "increment")
    sigma_m: float = Field(0.01, gt=0, description="wheel increment: horizontal std")
    scale_sigma: float = Field(0.015, ge=0, description="wheel increment: extra along-track std per metre")
    sigma_rad: float = Field(0.0003, gt=0, description="wheel increment: heading std after the gyro-bias "
                             "calibration (gangnam: 0.009-0.012 deg RMS per scan)")
    height_sigma_m: float = Field(0.03, gt=0, description="wheel increment: height std (planar model; bridge and "
                                  "fused)")
    tilt_sigma_rad: float = Field(0.005, gt=0, description="wheel increment: roll/pitch std (bridge and fused)")
    fusion: bool = Field(True, description="also put the calibrated wheel increment beside every accepted ICP edge: "
                         "it fixes the along-track direction, which ICP gets 1-4 cm wrong per edge in streets with few "
                         "cross structures")
    fusion_sigma_m: float = Field(0.002, gt=0, description="fused wheel increment: horizontal std (gangnam vs "
                                  "truth: 1.2 mm along, 0.05 mm across per scan; real vehicles slip sideways in turns: "
                                  "calibrate per vehicle)")
    fusion_scale_sigma: float = Field(0.001, ge=0, description="fused: extra along-track std per metre (residual of "
                                      "the per-drive scale calibration)")
    fusion_sigma_rad: float = Field(0.003, gt=0, description="fused: heading std, loose on purpose (the gyro bias "
                                    "drifts, and ICP's 0.005 deg per edge is better)")

    @property
    def bridge_noise(self) -> WheelNoise | None:
        """The bridge's noise; None when ``bridges`` is off."""
        return WheelNoise(self.sigma_m, self.scale_sigma, self.sigma_rad, self.height_sigma_m,
                          self.tilt_sigma_rad) if self.bridges else None

    @property
    def fusion_noise(self) -> WheelNoise | None:
        """The fused increment's noise; None when ``fusion`` is off."""
        return WheelNoise(self.fusion_sigma_m, self.fusion_scale_sigma, self.fusion_sigma_rad, self.height_sigma_m,
                          self.tilt_sigma_rad) if self.fusion else None


class RegistrationSigma(Params):
    """Added in quadrature to every ICP registration's own std (consecutive and span edges; the point-to-plane
    Hessian counts every point as independent evidence; docs/posegraph.md Known limits)."""

    along_m: float = Field(0.006, ge=0, description="along-track (the worst calibration seed, tiny 7, needs 0.006, "
                           "demo seed 1 0.003)")
    cross_m: float = Field(0.0, ge=0, description="cross-track (no calibration seed needs it)")
    yaw_deg: float = Field(0.02, ge=0, description="heading (tiny seed 7 0.019, demo seed 1 0.003; 0: the "
                           "registration's information alone)")

    @property
    def noise(self) -> RegistrationNoise:
        return RegistrationNoise(self.along_m, self.cross_m, math.radians(self.yaw_deg))


class FactorConfig(Params):
    """Between factors along a drive: a weak bridge of ``failed_edge_sigma_*`` over a missing or rejected ICP
    edge, the wheel increment as the bridge where the drive has one and beside every accepted edge (``wheel``), the
    odometry's span edges under a robust kernel, and the registration noise added to every ICP edge."""

    failed_edge_sigma_m: float = Field(0.15, gt=0, description="std of a bridge over a missing/failed ICP edge (the "
                                       "10 Hz GNSS/INS increment: ~0.1 m RMS on the simulator)")
    failed_edge_sigma_rad: float = Field(0.003, gt=0, description="same, rotation (INS increments ~0.001 rad)")
    wheel: WheelConfig = Field(default_factory=WheelConfig)
    registration: RegistrationSigma = Field(default_factory=RegistrationSigma)
    span_edges: bool = Field(True, description="put the odometry's accepted span edges (scans N apart) into the "
                             "graph beside the consecutive ones")
    span_edge_kernel: Kernel = Field("huber", description="robust kernel of the span edges")
    span_edge_kernel_k: float = Field(2.0, gt=0, description="span-edge kernel width in whitened units (gangnam "
                                      "no survey, spans 10/30/90: k 2 abs 0.281 m, 1 0.289, none 0.304)")

    @property
    def wheel_bridge(self) -> WheelNoise | None:
        return self.wheel.bridge_noise

    @property
    def wheel_fusion(self) -> WheelNoise | None:
        return self.wheel.fusion_noise

    @property
    def registration_sigma(self) -> RegistrationNoise:
        return self.registration.noise

    @property
    def uses_wheel(self) -> bool:
        """Whether any factor needs the drive's wheel odometry."""
        return self.wheel.bridges or self.wheel.fusion


class _Level(Params):
    """Roll/pitch a source leaves unknown (GNSS without attitude, a prior trajectory with NaN std)."""

    unknown_roll_pitch_sigma_rad: float = Field(
        0.05, gt=0, description="a weak 'vehicle roughly level' gravity prior (road grades of a few degrees) that "
                                "only keeps the graph determined; ICP road planes and GNSS heights carry the real "
                                "roll/pitch")


class GnssConfig(_Level):
    """GNSS position factors (one per ``every_s``, reported std x ``std_inflation`` floored at ``min_std_m``,
    robust kernel, a Gauss-Markov bias of correlation time ``bias_tau_s``) and INS attitude priors on the same
    epochs (roll/pitch; yaw only with ``heading_prior``)."""

    every_s: float = Field(1.0, ge=0, description="one GNSS factor per this many seconds (0: every scan)")
    std_inflation: float = Field(3.0, ge=1, description="receivers understate their error in canyons")
    min_std_m: float = Field(0.05, gt=0)
    kernel: Kernel = "huber"
    kernel_k: float = Field(1.345, gt=0, description="kernel width in whitened units")
    lever_arm_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="antenna in the vehicle frame")
    bias_tau_s: float = Field(60.0, ge=0, description="correlation time of the GNSS bias (Gauss-Markov states in the "
                              "graph); 0: treat GNSS errors as white noise")
    white_sigma_m: float = Field(0.05, gt=0, description="std of a fix around antenna position + bias")
    attitude_sigma_rad: float = Field(0.005, gt=0, description="INS roll/pitch prior (gravity anchor)")
    heading_prior: bool = Field(False, description="INS yaw as a prior per GNSS epoch; off: heading from ICP, loops "
                                "and the GNSS track (the INS heading error is a minute-scale bias; docs/posegraph.md)")
    heading_std_inflation: float = Field(3.0, ge=1, description="INS yaw std inflation (when heading_prior)")


class PriorConfig(_Level):
    """A drive without GNSS: its prior trajectory and start pose as factors (``factors/prior.py``)."""

    every_s: float = Field(1.0, ge=0, description="one prior-trajectory factor per this many seconds (0: every "
                           "scan); the trajectory's errors are correlated along it, as GNSS's")
    kernel: Kernel = Field("huber", description="robust kernel of the prior trajectory's factors (not the start "
                           "pose's)")
    kernel_k: float = Field(1.345, gt=0, description="prior-trajectory kernel width in whitened units")


class LoopVerifyConfig(Params):
    """The ICP verification of one loop candidate (``loops.verify.verify_loop``): coarse-to-fine GICP stages,
    the alignment score's search radius and plane tolerance, and the acceptance gates."""

    coarse_voxel_m: float = Field(1.0, gt=0, description="first GICP stage (pulls in a 1-2 m prior)")
    coarse_corr_m: float = Field(3.0, gt=0)
    voxel_m: float = Field(0.4, gt=0, description="fine GICP stages (max_corr_m, then max_corr_m / 2)")
    max_corr_m: float = Field(1.0, gt=0)
    relative_tolerance: float = Field(1e-4, gt=0, lt=1, description=(
        "each GICP stage stops when an iteration changes its fitness and inlier RMSE by less than this share "
        "(open3d's default 1e-6: 22 % slower on gangnam loops, results within 3 mm, no verdict changed)"))
    ground_split: bool = Field(False, description=(
        "an accepted loop is verified again on the structure above the two scans' road planes (height/roll/pitch "
        "from the planes), from its result, and replaced when that moves it less than ground_split_max_shift_m: the "
        "road pulled scans a few metres apart towards zero offset; off by default until measured on more seeds "
        "(docs/posegraph.md)"))
    ground_split_max_shift_m: float = Field(0.3, gt=0, description="the ground-split refinement replaces the loop "
                                            "when it moves it less than this")
    ground_tolerance_m: float = Field(0.25, gt=0, description="points this near a scan's road plane are road")
    inlier_m: float = Field(1.0, gt=0, description="scoring: nearest target point searched within this")
    plane_tol_m: float = Field(0.1, gt=0, description="scoring: inlier if its point-to-plane distance is below")
    min_fitness: float = Field(0.5, ge=0, le=1, description="share of inliers (true loops 0.53-0.73, scans 15-25 m "
                               "apart 0.08-0.45 on tiny; docs/posegraph.md)")
    max_rmse_m: float = Field(0.05, gt=0, description="point-to-plane RMS of the inliers (true 0.016-0.04 m)")
    max_correction_m: float = Field(4.0, gt=0, description="ICP vs prior relative pose")
    max_correction_rad: float = Field(0.2, gt=0)
    consistency_m: float = Field(0.1, gt=0, description="two ICP starts must agree within this")
    min_sigma_m: float = Field(0.02, gt=0)
    min_sigma_rad: float = Field(0.005, gt=0, description="loops fix positions; the map's heading is INS-grade "
                                 "(0.2-0.4 deg), tighter loops fight it")


class _Parallel(Params):
    """A step whose independent items run in parallel processes from ``parallel_min_items`` on."""

    parallel_min_items: int = Field(32, ge=1, description="independent registrations run in parallel processes (or "
                                    "cluster tasks) from this many on; fewer run in the stage's own process. Results "
                                    "do not depend on it")

    def workers(self, n_items: int) -> int | None:
        """All the machine's processes (None) from ``parallel_min_items`` independent items on, else this one."""
        return None if n_items >= self.parallel_min_items else 1


class WideLoopConfig(Params):
    """The wide loop search (``loops/wide.py``): where no GNSS fix, ENU prior or survey anchor holds a drive, the
    search region is the odometry's accumulated uncertainty of the relative position (a Mahalanobis gate), candidates
    are matched by a global registration (FPFH + RANSAC) then GICP, kept only when pairwise consistent (PCM), and the
    search runs again on the solved estimate. Drives with GNSS are searched as before."""

    enabled: bool = True
    sigmas: float = Field(3.0, gt=0, description="a target is a candidate when its estimated offset less "
                          "loops.radius_m is within this many sigma")
    min_sigma_m: float = Field(3.0, gt=0, description="only where the relative position's std exceeds this (below "
                               "it loops.radius_m covers sigmas sigma)")
    stride_m: float = Field(15.0, gt=0, description="one query scan per this much travel")
    max_per_scan: int = Field(4, ge=1, description="targets per query scan")
    target_spacing_m: float = Field(8.0, ge=0, description="a query's targets at least this far apart along their "
                                    "pass")
    rounds: int = Field(3, ge=1, description="rounds of search, verification and solve")
    global_voxel_m: float = Field(1.0, gt=0, description="voxel of the global registration (FPFH radius 5x, RANSAC "
                                  "correspondence 1.5x)")
    yaw_slack_deg: float = Field(5.0, ge=0, description="the global match's heading may differ from the estimate's "
                                 "by 3 sigma of the chain's heading std and this in quadrature")
    min_consistent: int = Field(2, ge=1, description="the loosely held drives' loops are accepted only as a "
                                "pairwise-consistent set of at least this many")


class LoopConfig(_Parallel):
    """Loop closures: candidates (one query per ``stride_m`` of travel, a reference drive's onto the map one per
    ``reference_stride_m``, other passes within ``radius_m``), their verification, the kernel of the accepted loops
    and the pass-3 gate; candidates run in parallel processes from ``parallel_min_items`` on. With survey anchors,
    only query poses that the anchors within ``survey_window_m`` of travel hold to less than ``survey_sigma_m`` in
    one direction or none look for loops (window 0: all)."""

    radius_m: float = Field(12.0, gt=0, description="candidate search radius on the pass-1 estimate (two drives in "
                            "different lanes of one street are 3.5-7 m apart)")
    min_separation_s: float = Field(30.0, ge=0, description="same drive: minimum time between scans")
    stride_m: float = Field(5.0, gt=0, description="one loop query scan per this much travel")
    max_per_scan: int = Field(2, ge=1)
    reference_stride_m: float = Field(10.0, gt=0, description=(
        "a reference (evaluation) drive's loops onto the fixed map: one query scan per this much travel "
        "(docs/posegraph.md, 'The reference drive's loops')"))
    incremental_max_per_scan: int = Field(1, ge=1, description="incremental solve (rebuild's default): loop targets "
                                          "per query scan of a new drive; the map is held, one pass of it ties the "
                                          "drive (stages/posegraph/incremental.py)")
    survey_window_m: float = Field(50.0, ge=0, description=(
        "with survey anchors, loop candidates are sought only at query scans that the accepted horizontal anchors of "
        "their drive within this much travel do not hold (survey_sigma_m): where the anchors hold each pass, they tie "
        "the passes to each other through the survey (docs/posegraph.md, 'Loops where the survey leaves a drive "
        "free'). 0: loops at every query scan (after the anchors)"))
    survey_sigma_m: float = Field(0.05, gt=0, description=(
        "a query scan is held when those anchors' summed horizontal information gives a std below this in its "
        "weaker direction (lane lines alone fix the position across the road, not along it)"))
    verify: LoopVerifyConfig = Field(default_factory=LoopVerifyConfig)
    wide: WideLoopConfig = Field(default_factory=WideLoopConfig)
    pcm_probability: float = Field(0.99, gt=0, lt=1, description="pairwise consistency: chi-square gate (3 dof) of a "
                                   "loop pair's cycle through the odometry")
    pcm_window_m: float = Field(100.0, gt=0, description="pairwise consistency: two loops are checked only when both "
                                "odometry segments between them are shorter than this travel (longer ones: the "
                                "odometry's biases exceed its covariance)")
    kernel: Literal["cauchy", "huber", "gnc"] = "cauchy"
    kernel_k: float = Field(3.0, gt=0)
    max_whitened_residual: float = Field(30.0, gt=0, description="post-check: reject loops above")


class GroundAnchorConfig(Params):
    """The vertical survey anchor of one keyframe (``anchors.survey_anchor.anchor_scan``): GICP of its points below
    ``max_height_m`` onto the survey cropped to ``crop_m``, both at ``voxel_m``, and its gates."""

    crop_m: float = Field(40.0, gt=0)
    max_height_m: float = Field(0.5, description="scan points below this (vehicle frame) are ground/curb")
    voxel_m: float = Field(0.2, gt=0, description="voxel of the scan and the survey in the registration")
    min_fitness: float = Field(0.5, ge=0, le=1)
    max_rmse_m: float = Field(0.25, gt=0, description="open3d inlier RMSE at 1 m (0.17-0.22 m measured)")
    min_sigma_m: float = Field(0.02, gt=0)
    min_sigma_rad: float = Field(0.001, gt=0)
    vertical_only: bool = Field(True, description="anchor height/roll/pitch only: the survey has no vertical "
                                "structure, its horizontal fit slides (docs/posegraph.md)")


class MarkingAnchorConfig(Params):
    """The horizontal survey anchor of one keyframe (``anchors.survey_markings.marking_anchor``): its marking
    submap, the search, the anchor std from the peak's width, the heading search, the survey's raster."""

    half_travel_m: float = Field(8.0, gt=0, description="submap: scans within this travel")
    max_scans: int = Field(10, ge=0, description="submap: at most this many scans each side")
    scan_step: int = Field(2, ge=1, description="submap: every N-th scan of that window (and the keyframe's own); "
                           "the poses within 1 mm of every scan's (docs/posegraph.md)")
    search_m: float = Field(2.0, gt=0, description="horizontal search (the pass-1 estimate is GNSS-level: RMS 0.6 m, "
                            "max 1.6 m on the simulator)")
    sigma_scale: float = Field(0.2, gt=0, description="anchor std = the correlation peak's width x this (demo, 112 "
                               "fixed directions vs truth: errors 0.010 m RMS where the width is ~0.11 m, i.e. 0.06; "
                               "0.2 keeps a margin)")
    min_sigma_m: float = Field(0.01, gt=0, description="floor of the anchor std")
    yaw_search_deg: float = Field(1.5, ge=0, description="the marking submap is also turned about its keyframe "
                                  "within +-this (0: translation only, whose shift inherits part of the estimate's "
                                  "heading error)")
    yaw_step_deg: float = Field(0.5, gt=0, description="grid step of that search (then a parabola)")
    raster: MarkingRasterSettings = Field(default_factory=MarkingRasterSettings, description="how the survey's "
                                          "marking mask is rasterized (the pose graph's own settings: a "
                                          "markings-stage override does not reach them)")


class AnchorConfig(_Parallel):
    """Survey anchors: one keyframe per ``stride_m``, its ground registration, its marking match (when
    ``use_markings``; heading prior of ``yaw_sigma_deg``, 0: none), the consensus check of the horizontal anchors,
    keyframes matched in blocks of ``block``, in parallel processes from ``parallel_min_items`` on; matched again
    from the anchored estimate (at most ``rounds`` in all) while a round moves a pose more than ``round_tol_*``."""

    stride_m: float = Field(10.0, gt=0)
    ground: GroundAnchorConfig = Field(default_factory=GroundAnchorConfig)
    use_markings: bool = Field(True, description="also anchor horizontally: match each keyframe's road-marking "
                               "points (a few scans) to the survey's marking mask")
    markings: MarkingAnchorConfig = Field(default_factory=MarkingAnchorConfig)
    yaw_sigma_deg: float = Field(0.08, ge=0, description="heading prior at the marking submap's matched heading, "
                                 "this std (tiny calibration seeds 7, 21, 22: accepted anchors' heading RMS 0.081, "
                                 "0.037, 0.072 deg; the worst seed's); 0: no heading information from the markings")
    consensus_window_m: float = Field(300.0, gt=0, description="horizontal anchors are checked against the other "
                                      "anchors of their drive within this travel (anchor_consensus.py)")
    consensus_drift_sigma_m: float = Field(0.10, gt=0, description="how much the pass-1 estimate's error may differ "
                                           "between anchors of one window")
    consensus_probability: float = Field(0.99, gt=0, lt=1, description="chi-square gate of that check")
    block: int = Field(8, ge=1, description="consecutive keyframes matched on the markings by one worker (they share "
                       "submap scans); speed only, results do not depend on it")
    rounds: int = Field(3, ge=1, description="anchoring rounds at most: the anchors are matched again from the "
                        "anchored estimate while the previous round turned a pose by more than round_tol_deg or moved "
                        "one by more than round_tol_m (docs/posegraph.md)")
    round_tol_m: float = Field(1.0, gt=0, description="half the marking search (markings.search_m): the shift search "
                               "is exhaustive, so an estimate that was only shifted, by less than this, is matched the "
                               "same again")
    round_tol_deg: float = Field(0.05, gt=0, description="a round that turned no pose by more than this (and moved "
                                 "none by more than round_tol_m) is the last: the heading error is what a match "
                                 "inherits through its submap's lever arm")


class SolveConfig(Params):
    """Levenberg-Marquardt stopping rules, the tight prior on map poses held fixed for a reference drive,
    whether the marginal covariances are computed, and how many pose pairs per distance bin give the map's
    error-correlation kernel (0: none; ``error_correlation.py``)."""

    max_iterations: int = Field(100, ge=1)
    lm_relative_error_tol: float = Field(1e-5, gt=0, description="Levenberg-Marquardt stops when an iteration lowers "
                                         "the error by less than this share (gangnam, 8448 poses: 1e-7 -> 15 "
                                         "iterations, 1e-5 -> 9, error 4889.71 vs 4889.73, docs/posegraph.md)")
    fixed_prior_sigma_m: float = Field(1e-3, gt=0, description="map poses held fixed for reference drives")
    compute_marginals: bool = True
    error_kernel_pairs_per_bin: int = Field(60, ge=0, description="pose pairs per distance bin (0-15, 15-40, 40-80, "
                                            "80-150 m) whose joint marginals give the map's error-correlation kernel "
                                            "(error_correlation.py; the map publishes it for localizers); 0: none")

    def lm_kwargs(self) -> dict:
        """The keywords of ``factors.graph.optimize``."""
        return {"max_iterations": self.max_iterations, "relative_error_tol": self.lm_relative_error_tol}


class RegionConfig(Params):
    """The region-wise solve (``regions.py``; ``cornermap maps reoptimize``)."""

    max_poses: int = Field(0, ge=0, description="most poses of one region when the graph is solved region by region "
                           "(recursive bisection, a condensed separator between regions, the same optimum); 0: one "
                           "joint solve (build, rebuild)")
    rounds: int = Field(20, ge=1, description="most separator updates")
    tol_m: float = Field(1e-4, gt=0, description="a round that moves no separator more than this (and 0.1 of it in "
                         "radians) ends it")
