"""Parameters of the posegraph stage (defaults measured on simulated drives, see docs/posegraph.md)."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.declare import Params
from stages.common.marking_raster.settings import MarkingRasterSettings


class PosegraphParams(Params):
    # odometry edges
    failed_edge_sigma_m: float = Field(0.15, gt=0, description="std of a bridge over a missing/failed ICP edge "
                                       "(the 10 Hz GNSS/INS increment: ~0.1 m RMS on the simulator)")
    failed_edge_sigma_rad: float = Field(0.003, gt=0, description="same, rotation (INS increments ~0.001 rad)")
    wheel_bridges: bool = Field(True, description="where ICP failed and the drive has wheel odometry, bridge with "
                                "the wheel increment (gangnam: 1.2 % scale error, 0.01 deg yaw per scan) instead of "
                                "the GNSS/INS increment")
    wheel_sigma_m: float = Field(0.01, gt=0, description="wheel increment: horizontal std")
    wheel_scale_sigma: float = Field(0.015, ge=0, description="wheel increment: extra along-track std per metre")
    wheel_sigma_rad: float = Field(0.0003, gt=0, description="wheel increment: heading std after the gyro-bias "
                                   "calibration (gangnam: 0.009-0.012 deg RMS per scan)")
    wheel_height_sigma_m: float = Field(0.03, gt=0, description="wheel increment: height std (planar model)")
    wheel_tilt_sigma_rad: float = Field(0.005, gt=0, description="wheel increment: roll/pitch std")
    wheel_fusion: bool = Field(True, description="also put the calibrated wheel increment beside every accepted "
                               "ICP edge: it fixes the along-track direction, which ICP gets 1-4 cm wrong per edge in "
                               "streets with few cross structures (gangnam rel 10 m: 0.036 -> 0.024 m, dead "
                               "reckoning)")
    wheel_fusion_sigma_m: float = Field(0.002, gt=0, description="fused wheel increment: horizontal std "
                                        "(gangnam vs truth: 1.2 mm along, 0.05 mm across per scan; real vehicles "
                                        "slip sideways in turns: calibrate per vehicle)")
    wheel_fusion_scale_sigma: float = Field(0.001, ge=0, description="fused: extra along-track std per metre "
                                            "(residual of the per-drive scale calibration)")
    wheel_fusion_sigma_rad: float = Field(0.003, gt=0, description="fused: heading std, loose on purpose (the gyro "
                                          "bias drifts, and ICP's 0.005 deg per edge is better)")
    icp_edge_sigma_along_m: float = Field(0.006, ge=0, description="added in quadrature to every ICP registration's "
                                          "own along-track std (consecutive and span edges; the point-to-plane "
                                          "Hessian counts every point as independent evidence; docs/posegraph.md "
                                          "Known limits: the worst calibration seed, tiny 7, needs 0.006, demo seed "
                                          "1 0.003)")
    icp_edge_sigma_cross_m: float = Field(0.0, ge=0, description="same, cross-track (no calibration seed needs it)")
    icp_edge_sigma_yaw_deg: float = Field(0.02, ge=0, description="same, heading (tiny seed 7 0.019, demo seed 1 "
                                          "0.003; 0: the registration's information alone)")
    span_edges: bool = Field(True, description="put the odometry's accepted span edges (scans N apart) into the "
                             "graph beside the consecutive ones")
    span_edge_kernel: Literal["huber", "cauchy", "none"] = Field("huber", description="robust kernel of the span "
                                                                 "edges")
    span_edge_kernel_k: float = Field(2.0, gt=0, description="span-edge kernel width in whitened units (gangnam "
                                      "no survey, spans 10/30/90: k 2 abs 0.281 m, 1 0.289, none 0.304)")
    # GNSS / INS priors
    gnss_std_inflation: float = Field(3.0, ge=1, description="receivers understate their error in canyons")
    gnss_min_std_m: float = Field(0.05, gt=0)
    gnss_every_s: float = Field(1.0, ge=0, description="one GNSS factor per this many seconds (0: every scan)")
    gnss_bias_tau_s: float = Field(60.0, ge=0, description="correlation time of the GNSS bias (Gauss-Markov "
                                   "states in the graph); 0: treat GNSS errors as white noise")
    gnss_white_sigma_m: float = Field(0.05, gt=0, description="std of a fix around antenna position + bias")
    gnss_kernel: Literal["huber", "cauchy", "none"] = "huber"
    gnss_kernel_k: float = Field(1.345, gt=0, description="kernel width in whitened units")
    gnss_lever_arm_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0),
                                                          description="antenna in the vehicle frame")
    attitude_sigma_rad: float = Field(0.005, gt=0, description="INS roll/pitch prior (gravity anchor)")
    unknown_roll_pitch_sigma_rad: float = Field(
        0.05, gt=0, description="GNSS without roll/pitch: a weak 'vehicle roughly level' gravity prior (road grades "
                                "of a few degrees) that only keeps the graph determined; ICP road planes and GNSS "
                                "heights carry the real roll/pitch")
    heading_prior: bool = Field(False, description="INS yaw as a prior per GNSS epoch; off: heading from ICP, "
                                "loops and the GNSS track (the INS heading error is a minute-scale bias; with the "
                                "prior demo heading RMS 0.335 deg, without 0.099, docs/posegraph.md)")
    heading_std_inflation: float = Field(3.0, ge=1, description="INS yaw std inflation (when heading_prior)")
    # a drive without GNSS: its prior trajectory and start pose (poses_prior)
    prior_every_s: float = Field(1.0, ge=0, description="without GNSS: one prior-trajectory factor per this many "
                                 "seconds (0: every scan); the trajectory's errors are correlated along it, as GNSS's")
    prior_kernel: Literal["huber", "cauchy", "none"] = Field("huber", description="robust kernel of the prior "
                                                             "trajectory's factors (not the start pose's)")
    prior_kernel_k: float = Field(1.345, gt=0, description="prior-trajectory kernel width in whitened units")
    # loop closures
    loop_radius_m: float = Field(12.0, gt=0, description="candidate search radius on the pass-1 estimate (two "
                                 "drives in different lanes of one street are 3.5-7 m apart)")
    loop_min_separation_s: float = Field(30.0, ge=0, description="same drive: minimum time between scans")
    loop_stride_m: float = Field(5.0, gt=0, description="one loop query scan per this much travel")
    loop_max_per_scan: int = Field(2, ge=1)
    loop_reference_stride_m: float = Field(10.0, gt=0, description=(
        "a reference (evaluation) drive's loops onto the fixed map: one query scan per this much travel (demo "
        "calibration seeds 1-3: 5 -> 10 m halves its candidates, its poses 1-2 mm RMS further from the truth; "
        "docs/posegraph.md, 'The reference drive's loops')"))
    loop_survey_window_m: float = Field(50.0, ge=0, description=(
        "with survey anchors, loop candidates are sought only at query scans that the accepted horizontal anchors of "
        "their drive within this much travel do not hold (loop_survey_sigma_m): where the anchors hold each pass, "
        "they tie the passes to each other through the survey (docs/posegraph.md, 'Loops where the survey leaves a "
        "drive free'). 0: loops at every query scan (after the anchors)"))
    loop_survey_sigma_m: float = Field(0.05, gt=0, description=(
        "a query scan is held when those anchors' summed horizontal information gives a std below this in its "
        "weaker direction (lane lines alone fix the position across the road, not along it)"))
    loop_wide: bool = Field(True, description=(
        "the wide loop search (stages/posegraph/loops/wide.py): where no GNSS fix, ENU prior or survey anchor holds a "
        "drive, the search region is the odometry's accumulated uncertainty of the relative position (a Mahalanobis "
        "gate), candidates are matched by a global registration (FPFH + RANSAC) then GICP, kept only when pairwise "
        "consistent (PCM), and the search runs again on the solved estimate. Drives with GNSS are searched as before"))
    loop_wide_sigmas: float = Field(3.0, gt=0, description="wide search: a target is a candidate when its estimated "
                                    "offset less loop_radius_m is within this many sigma")
    loop_wide_min_sigma_m: float = Field(3.0, gt=0, description="wide search only where the relative position's std "
                                         "exceeds this (below it loop_radius_m covers loop_wide_sigmas sigma)")
    loop_wide_stride_m: float = Field(15.0, gt=0, description="wide search: one query scan per this much travel")
    loop_wide_max_per_scan: int = Field(4, ge=1, description="wide search: targets per query scan")
    loop_wide_target_spacing_m: float = Field(8.0, ge=0, description="wide search: a query's targets at least this "
                                              "far apart along their pass")
    loop_wide_rounds: int = Field(3, ge=1, description="wide search: rounds of search, verification and solve")
    loop_wide_global_voxel_m: float = Field(1.0, gt=0, description="wide search: voxel of the global registration "
                                            "(FPFH radius 5x, RANSAC correspondence 1.5x)")
    loop_wide_yaw_slack_deg: float = Field(5.0, ge=0, description="wide search: the global match's heading may differ "
                                           "from the estimate's by 3 sigma of the chain's heading std and this in "
                                           "quadrature")
    loop_wide_min_consistent: int = Field(2, ge=1, description="wide search: the loosely held drives' loops are "
                                          "accepted only as a pairwise-consistent set of at least this many")
    loop_pcm_probability: float = Field(0.99, gt=0, lt=1, description="pairwise consistency: chi-square gate (3 dof) "
                                        "of a loop pair's cycle through the odometry")
    loop_pcm_window_m: float = Field(100.0, gt=0, description="pairwise consistency: two loops are checked only when "
                                     "both odometry segments between them are shorter than this travel (longer ones: "
                                     "the odometry's biases exceed its covariance)")
    loop_coarse_voxel_m: float = Field(1.0, gt=0, description="first GICP stage (pulls in a 1-2 m prior)")
    loop_coarse_corr_m: float = Field(3.0, gt=0)
    loop_voxel_m: float = Field(0.4, gt=0, description="fine GICP stages (max_corr, then max_corr / 2)")
    loop_max_corr_m: float = Field(1.0, gt=0)
    loop_relative_tolerance: float = Field(1e-4, gt=0, lt=1, description=(
        "each GICP stage stops when an iteration changes its fitness and inlier RMSE by less than this share "
        "(open3d's default 1e-6: 22 % slower on gangnam loops, results within 3 mm, no verdict changed)"))
    loop_ground_split: bool = Field(False, description=(
        "an accepted loop is verified again on the structure above the two scans' road planes (height/roll/pitch "
        "from the planes), from its result, and replaced when that moves it less than 0.3 m: the road pulled scans a "
        "few metres apart towards zero offset (demo seed 2: 0.12-0.14 m); off by default until measured on more "
        "seeds (docs/posegraph.md)"))
    loop_inlier_m: float = Field(1.0, gt=0, description="scoring: nearest target point searched within this")
    loop_plane_tol_m: float = Field(0.1, gt=0, description="scoring: inlier if its point-to-plane distance is below")
    loop_min_fitness: float = Field(0.5, ge=0, le=1, description="share of inliers (true loops 0.53-0.73, scans "
                                    "15-25 m apart 0.08-0.45 on tiny; docs/posegraph.md)")
    loop_max_rmse_m: float = Field(0.05, gt=0, description="point-to-plane RMS of the inliers (true 0.016-0.04 m)")
    loop_max_correction_m: float = Field(4.0, gt=0, description="ICP vs prior relative pose")
    loop_max_correction_rad: float = Field(0.2, gt=0)
    loop_consistency_m: float = Field(0.1, gt=0, description="two ICP starts must agree within this")
    loop_kernel: Literal["cauchy", "huber", "gnc"] = "cauchy"
    loop_kernel_k: float = Field(3.0, gt=0)
    loop_max_whitened_residual: float = Field(30.0, gt=0, description="post-check: reject loops above")
    loop_min_sigma_m: float = Field(0.02, gt=0)
    loop_min_sigma_rad: float = Field(
        0.005,
        gt=0,
        description="loops fix positions; the map's heading is INS-grade (0.2-0.4 deg), tighter loops fight it",
    )
    # survey anchoring
    survey_stride_m: float = Field(10.0, gt=0)
    survey_crop_m: float = Field(40.0, gt=0)
    survey_max_height_m: float = Field(0.5, description="scan points below this (vehicle frame) are ground/curb")
    survey_min_fitness: float = Field(0.5, ge=0, le=1)
    survey_max_rmse_m: float = Field(0.25, gt=0, description="open3d inlier RMSE at 1 m (0.17-0.22 m measured)")
    survey_min_sigma_m: float = Field(0.02, gt=0)
    survey_min_sigma_rad: float = Field(0.001, gt=0)
    survey_vertical_only: bool = Field(True, description="anchor height/roll/pitch only: the survey has no "
                                       "vertical structure, its horizontal fit slides (docs/posegraph.md)")
    survey_markings: bool = Field(True, description="also anchor horizontally: match each keyframe's road-marking "
                                  "points (a few scans) to the survey's marking mask")
    survey_marking_half_travel_m: float = Field(8.0, gt=0, description="submap: scans within this travel")
    survey_marking_max_scans: int = Field(10, ge=0, description="submap: at most this many scans each side")
    survey_marking_scan_step: int = Field(2, ge=1, description="submap: every N-th scan of that window (and the "
                                          "keyframe's own). 2 (chosen on demo seed 2 and gangnam seed 2): the "
                                          "marking step's first round 44.2 -> 29.5 s on gangnam seed 1, the poses "
                                          "within 1 mm of every scan's (docs/posegraph.md)")
    survey_marking_search_m: float = Field(2.0, gt=0, description="horizontal search (the pass-1 estimate is "
                                           "GNSS-level: RMS 0.6 m, max 1.6 m on the simulator)")
    survey_marking_sigma_scale: float = Field(0.2, gt=0, description="anchor std = the correlation peak's width "
                                              "x this (demo, 112 fixed directions vs truth: errors 0.010 m RMS "
                                              "where the width is ~0.11 m, i.e. 0.06; 0.2 keeps a margin)")
    survey_marking_min_sigma_m: float = Field(0.01, gt=0, description="floor of the anchor std")
    survey_marking_yaw_search_deg: float = Field(1.5, ge=0, description="the marking submap is also turned about "
                                                 "its keyframe within +-this (0: translation only, whose shift "
                                                 "inherits part of the estimate's heading error)")
    survey_marking_yaw_step_deg: float = Field(0.5, gt=0, description="grid step of that search (then a parabola)")
    survey_marking_yaw_sigma_deg: float = Field(0.08, ge=0, description="heading prior at the submap's matched "
                                                "heading, this std (tiny calibration seeds 7, 21, 22, accepted "
                                                "anchors of the last round against the truth's heading: RMS 0.081, "
                                                "0.037, 0.072 deg; the worst seed's); 0: no heading information "
                                                "from the markings")
    survey_marking_consensus_window_m: float = Field(300.0, gt=0, description="horizontal anchors are checked "
                                                     "against the other anchors of their drive within this travel "
                                                     "(anchor_consensus.py)")
    survey_marking_consensus_drift_sigma_m: float = Field(0.10, gt=0, description="how much the pass-1 estimate's "
                                                          "error may differ between anchors of one window")
    survey_marking_consensus_probability: float = Field(0.99, gt=0, lt=1, description="chi-square gate of that check")
    survey_rounds: int = Field(3, ge=1, description="anchoring rounds at most: the anchors are matched again from the "
                               "anchored estimate while the previous round turned a pose by more than "
                               "survey_round_tol_deg or moved one by more than survey_round_tol_m (a match made from "
                               "an estimate 1 deg off loses the anchors the consensus check cannot reconcile; "
                               "docs/posegraph.md)")
    survey_round_tol_m: float = Field(1.0, gt=0, description="half the marking search (survey_marking_search_m): the "
                                      "shift search is exhaustive, so an estimate that was only shifted, by less than "
                                      "this, is matched the same again")
    survey_round_tol_deg: float = Field(0.05, gt=0, description="a round that turned no pose by more than this (and "
                                        "moved none by more than survey_round_tol_m) is the last: the heading error is "
                                        "what a match inherits through its submap's lever arm. The map-frame target's "
                                        "value (0.10 left tiny calibration seed 7 at -0.053 deg after one round)")
    parallel_min_items: int = Field(32, ge=1, description="independent registrations (loop candidates, survey "
                                    "anchors) run in parallel processes (or cluster tasks) from this many on; "
                                    "fewer run in the stage's own process. Results do not depend on it")
    survey_marking_block: int = Field(8, ge=1, description="consecutive keyframes matched on the markings by one "
                                      "worker (they share submap scans); speed only, results do not depend on it")
    survey_marking_raster: MarkingRasterSettings = Field(
        default_factory=MarkingRasterSettings, description="how the survey's marking mask is rasterized (the "
        "pose graph's own settings: a markings-stage override does not reach them)")
    # optimisation / outputs
    max_iterations: int = Field(100, ge=1)
    lm_relative_error_tol: float = Field(1e-5, gt=0, description="Levenberg-Marquardt stops when an iteration "
                                         "lowers the error by less than this share (gangnam, 8448 poses: 1e-7 "
                                         "-> 15 iterations, 1e-5 -> 9, error 4889.71 vs 4889.73, docs/posegraph.md)")
    fixed_prior_sigma_m: float = Field(1e-3, gt=0, description="map poses held fixed for reference drives")
    loop_incremental_max_per_scan: int = Field(1, ge=1, description="incremental solve (rebuild's default): "
                                               "loop targets per query scan of a new drive; the map is held, one "
                                               "pass of it ties the drive (stages/posegraph/incremental.py)")
    compute_marginals: bool = True
    error_kernel_pairs_per_bin: int = Field(60, ge=0, description="pose pairs per distance bin (0-15, 15-40, 40-80, "
                                            "80-150 m) whose joint marginals give the map's error-correlation "
                                            "kernel (error_correlation.py; the map publishes it for localizers); "
                                            "0: none")
    # region-wise solve (``cornermap maps reoptimize``; stages/posegraph/regions.py)
    region_max_poses: int = Field(0, ge=0, description="most poses of one region when the graph is solved region "
                                  "by region (recursive bisection, a condensed separator between regions, the same "
                                  "optimum); 0: one joint solve (build, rebuild)")
    region_rounds: int = Field(20, ge=1, description="region solve: most separator updates")
    region_tol_m: float = Field(1e-4, gt=0, description="region solve: a round that moves no separator more than "
                                "this (and 0.1 of it in radians) ends it")
