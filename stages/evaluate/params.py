"""Parameters of the evaluate stage: the EKF (Im et al. s.4), the MCL (Kim et al. s.2.3), the report."""
from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field, model_validator

from pipeline.declare import Params
from stages.common.localizer_defaults import CORNER_EKF, MARKINGS, MCL_MOTION

if TYPE_CHECKING:
    from stages.evaluate.config import EvaluationConfig, FieldConfig, TargetConfig
    from stages.evaluate.localize_ekf import EkfConfig
    from stages.evaluate.localize_mcl import MclConfig


class EvaluateParams(Params):
    methods: list[Literal["ekf", "mcl"]] = Field(["ekf", "mcl"], description="localizers; baselines always run")
    # EKF initialisation: the first GNSS/INS fix, its reported std floored by these (urban RTK/INS understates its
    # error: 0.5-2 m true vs 0.1-0.25 m reported in canyons), so the first corners can pull the filter in.
    init_sigma_xy_m: float = Field(CORNER_EKF.init_sigma_xy_m, gt=0, description="floor of the initial position std")
    init_sigma_yaw_deg: float = Field(CORNER_EKF.init_sigma_yaw_deg, gt=0,
                                      description="floor of the initial heading std")
    # EKF motion noise (ICP increments, eq. 2)
    icp_sigma_frac: float = Field(CORNER_EKF.icp_sigma_frac, ge=0,
                                  description="ICP translation std per metre travelled")
    icp_sigma_xy_m: float = Field(CORNER_EKF.icp_sigma_xy_m, ge=0, description="ICP translation std floor per scan")
    icp_sigma_yaw_deg: float = Field(CORNER_EKF.icp_sigma_yaw_deg, ge=0,
                                     description="ICP heading std per scan: the consecutive ICP edges' "
                                     "heading error vs truth on the tiny calibration seeds 7 / 21 / 22 with the "
                                     "simulator's sensor effects and traffic: 0.010-0.023 deg RMS, in turns as on "
                                     "straights (bench_posegraph_root's edge table; docs/evaluation.md). The previous "
                                     "0.004 came from gangnam's edges before those effects (0.005 deg RMS)")
    icp_sigma_yaw_frac: float = Field(0.0, ge=0, description="ICP heading std per radian turned (0: turns are no "
                                      "worse, measured)")
    icp_wheel_gate_deg: float = Field(0.05, ge=0, description="an ICP increment whose heading change differs from "
                                      "the wheel/gyro increment's by more than this is replaced by the wheel/gyro "
                                      "increment, as a failed one is (0 = failed edges only)")
    # EKF motion model. wheel_bias: the state carries the gyro bias and the wheel scale error; the wheel/gyro
    # increment is the motion prior and the ICP increment, weighted by the registration's own information (a
    # degenerate street's axis weighs nothing), measures it when consistent (chi-square gate below); the bias is
    # estimated while ICP holds and carried, with its random walk, when it does not. icp: the paper's ICP-only
    # motion with the wheel fallback and the angle gate above (the default: wheel_bias is overconfident at corner
    # epochs on the tiny validation seeds, NEES 3.6-8.0; CHANGELOG.md, issue 28).
    ekf_motion: Literal["wheel_bias", "icp"] = Field("icp", description="EKF motion model")
    ekf_gyro_bias_sigma_deg_s: float = Field(0.115, gt=0, description="initial gyro bias std (MEMS spec, as the MCL)")
    ekf_gyro_bias_rw_deg_s_per_sqrt_s: float = Field(0.0057, ge=0, description="gyro bias random walk")
    ekf_wheel_scale_sigma: float = Field(0.01, gt=0, description="initial wheel-speed scale error std")
    ekf_wheel_scale_rw_per_sqrt_m: float = Field(1e-3, ge=0, description="wheel scale random walk")
    ekf_wheel_sigma_frac: float = Field(0.005, ge=0, description="wheel along-track noise per metre")
    ekf_wheel_sigma_lateral_frac: float = Field(0.002, ge=0, description="wheel across-track (slip) noise per metre")
    ekf_gyro_sigma_yaw_deg: float = Field(0.01, ge=0, description="gyro heading noise per scan (beside the bias)")
    ekf_gyro_sigma_yaw_frac: float = Field(0.005, ge=0, description="gyro scale error per radian turned")
    ekf_icp_gate_probability: float = Field(0.999, gt=0, lt=1, description="ICP increment vs wheel/gyro "
                                            "consistency gate (chi-square 3 dof)")
    # EKF association and measurement (s.3.3, eqs. 3-5)
    sensor_range_m: float = Field(CORNER_EKF.sensor_range_m, gt=0,
                                  description="map corners farther than this are not predicted")
    gate_probability: float = Field(0.99, gt=0, lt=1, description="Mahalanobis gate, chi-square 2 dof")
    angle_gate_deg: float = Field(15.0, gt=0, le=180, description="max wall direction difference")
    association: Literal["gnn", "nn"] = "gnn"
    range_sigma_floor_m: float = Field(CORNER_EKF.range_sigma_floor_m, ge=0,
                                       description="added to extracted corners' range std (gangnam "
                                       "drive 1: position NEES 2.2 for 2 dof; 0.03 gave 2.7, map corner errors are "
                                       "shared by consecutive epochs)")
    bearing_sigma_floor_deg: float = Field(CORNER_EKF.bearing_sigma_floor_deg, ge=0,
                                           description="added to extracted corners' bearing std")
    wall_heading_sigma_deg: float = Field(CORNER_EKF.wall_heading_sigma_deg, ge=0,
                                          description="heading from wall directions; 0 = off")
    ekf_map_consider: bool = Field(True, description="map-corner errors as Schmidt consider states (shared by every "
                                   "epoch using the corner, not fresh noise per epoch; evaluate/consider.py)")
    ekf_map_cov_scale: float = Field(1.0, gt=0, description="multiplies the map's stored corner covariances")
    ekf_map_corr_share: float = Field(CORNER_EKF.map_corr_share, ge=0, lt=1,
                                      description="with the consider states: correlation of two "
                                      "map corners' errors at distance d is share * exp(-d^2 / (2 L^2)), L = "
                                      "ekf_map_corr_length_m (corners seen from one stretch of the survey drive share "
                                      "its pose error)")
    ekf_map_corr_length_m: float = Field(CORNER_EKF.map_corr_length_m, gt=0, description="length of that correlation")
    ekf_map_corr_source: Literal["map", "params"] = Field(
        "map", description="map: the correlation the published map states (its pose graph's joint marginals, "
        "manifest corner_error_correlation) replaces ekf_map_corr_share / ekf_map_corr_length_m when it states one; "
        "params: those two values always")
    # icp motion model, issue 28 (heading between corners): the gyro bias as a 4th state. The wheel/gyro increments
    # that replace failed or gated ICP ones drift with it, so the heading std grows with the time spent on them
    # (as the error does), not with the square root of their number; the gyro's heading change also measures each
    # accepted ICP increment's, which estimates the bias while ICP holds (values: ekf_gyro_*; docs/evaluation.md).
    ekf_icp_gyro_bias_state: bool = Field(True, description="icp motion model: gyro bias state carried by the "
                                          "wheel/gyro fallback increments")
    ekf_icp_gyro_fusion: bool = Field(True, description="with ekf_icp_gyro_bias_state: the gyro's heading change "
                                      "also measures each accepted ICP increment's (estimates the bias)")
    ekf_heading_rw_deg_per_sqrt_s: float = Field(0.0, ge=0, description="icp motion model: heading random walk "
                                                 "beside icp_sigma_yaw_deg (0: none measured against the map "
                                                 "reference on the tiny calibration seeds)")
    ekf_icp_gyro_gate: bool = Field(True, description="with the fusion: ICP is gated against the bias-corrected "
                                    "gyro with the innovation's variance (chi-square 1 dof at "
                                    "ekf_icp_gate_probability) instead of icp_wheel_gate_deg (calibrated on "
                                    "tiny seeds 7/21/22, validated on tiny seeds 41-46)")
    ekf_markings: bool = Field(True, description="each scan's road features also measure the EKF's pose against "
                               "the map's marking raster, with the MCL's likelihood (mcl_sharpness, "
                               "mcl_effective_points, mcl_decorrelation_m, mcl_max_features): the lateral position "
                               "and heading between corners (evaluate/ekf_markings.py; on by the tiny calibration "
                               "seeds 7 / 21 / 22: EKF p99 0.193 / 0.084 / 0.083 m -> 0.097 / 0.057 / 0.047)")
    ekf_corner_decorrelation_m: float = Field(CORNER_EKF.corner_decorrelation_m, ge=0,
                                              description="a corner's range/bearing and wall-heading "
                                              "noise is divided by min(1, travel since the corner last measured "
                                              "the pose / this): looks from nearly the same place repeat most of "
                                              "the extraction error (0 = every look counts fully; 0.5 chosen on "
                                              "demo 1 and tiny 7 / 21 / 22 among 0.25 / 0.5 / 1: corner-epoch "
                                              "NEES share under the quantile 0.989 -> 0.999 on demo 1)")
    ekf_marking_min_info: float = Field(0.05, gt=0, description="a direction the markings inform less than this "
                                        "share of the prior's information is not measured")
    ekf_marking_map_sigma_m: float = Field(MARKINGS.map_sigma_m, ge=0,
                                           description="the marking raster's own local error per axis "
                                           "(a Gauss-Markov offset along the road, a consider parameter): the "
                                           "mapping drive's optimised poses vs the truth on the worst tiny "
                                           "calibration seed (7: 0.051 m horizontal RMS; bench_posegraph_eval)")
    ekf_marking_map_sigma_deg: float = Field(MARKINGS.map_sigma_deg, ge=0,
                                             description="its heading part (seed 7: 0.092 deg RMS)")
    ekf_marking_map_length_m: float = Field(MARKINGS.map_length_m, gt=0,
                                            description="its correlation length along the road (as "
                                            "ekf_map_corr_length_m)")
    # MCL (s.2.3) and road features (s.2.2). Wheel speed + gyro prediction through a per-particle wheel scale and
    # gyro bias; weights from the correlation of the scan's features with a distance likelihood field; low-variance
    # resampling; progressive correction and guarded injection (see localize_mcl.MclConfig for the measurements).
    n_particles: int = Field(1000, ge=10)
    seed: int = 0
    mcl_init_sigma_xy_m: float = Field(MCL_MOTION.init_sigma_xy_m, gt=0)
    mcl_init_sigma_yaw_deg: float = Field(MCL_MOTION.init_sigma_yaw_deg, gt=0)
    mcl_sigma_frac: float = Field(MCL_MOTION.sigma_frac, ge=0,
                                  description="along-track motion noise per metre (beside the scale)")
    mcl_sigma_lateral_frac: float = Field(MCL_MOTION.sigma_lateral_frac, ge=0,
                                          description="across-track motion noise per metre")
    mcl_sigma_xy_m: float = Field(MCL_MOTION.sigma_xy_m, ge=0,
                                  description="translation motion noise floor per moving scan")
    mcl_sigma_yaw_deg: float = Field(MCL_MOTION.sigma_yaw_deg, ge=0,
                                     description="heading motion noise per moving scan (beside the bias)")
    mcl_sigma_yaw_frac: float = Field(0.01, ge=0, description="heading motion noise per radian turned")
    mcl_init_sigma_scale: float = Field(0.01, ge=0, description="wheel-speed scale std per particle (0 = no state)")
    mcl_sigma_scale_per_sqrt_m: float = Field(1e-3, ge=0, description="random walk of the wheel scale")
    mcl_init_sigma_gyro_bias_deg_s: float = Field(0.115, ge=0, description="gyro bias std per particle, deg/s")
    mcl_sigma_gyro_bias_deg_s_per_sqrt_s: float = Field(0.0057, ge=0, description="random walk of the gyro bias")
    mcl_init_sigma_gyro_gain: float = Field(0.005, ge=0, description="gyro gain (scale factor) std about 1 per "
                                            "particle (0 = not a state): a turn's heading error is the gain's, "
                                            "systematic over the drive (0.5 %, a MEMS gyro's; tiny calibration "
                                            "seeds 7 / 21 / 22, mean |heading| over filter seeds 0-2: 0.213 / "
                                            "0.049 / 0.128 deg without, 0.171 / 0.045 / 0.137 with)")
    mcl_decorrelation_m: float = Field(MARKINGS.decorrelation_m, ge=0,
                                       description="travel after which a scan counts fully (0 = always)")
    mcl_sharpness: float = Field(MARKINGS.sharpness, gt=0,
                                 description="log-likelihood gain per effective feature point")
    mcl_effective_points: float = Field(MARKINGS.effective_points, gt=0)
    mcl_max_features: int = Field(400, ge=10)
    mcl_max_inject: float = Field(0.3, ge=0, le=1, description="share of particles a recovery may replace; 0 = off")
    mcl_inject_sigma_xy_m: float = Field(1.0, gt=0, description="spread of recovery candidates about the estimate")
    raster_field: Literal["distance", "blur"] = Field("distance", description="marking likelihood field: "
                                                      "exp(-d^2/2 sigma^2) of the distance to paint, or a blurred mask")
    raster_sigma_m: float = Field(MARKINGS.raster_sigma_m, gt=0, description="sigma of the distance likelihood field")
    raster_blur_m: float = Field(0.2, ge=0, description="Gaussian blur of the marking raster (raster_field=blur)")
    raster_coverage: bool = Field(True, description="count only the road features that fall where the map saw the "
                                  "ground (its point_count layer; beyond the survey 'no paint' is not known): MCL "
                                  "and the EKF's markings (tiny calibration seeds 7 / 21 / 22, MCL mean |heading| "
                                  "0.121 / 0.042 / 0.113 -> 0.048 / 0.027 / 0.037 deg)")
    raster_coverage_margin_m: float = Field(2.0, ge=0, description="the surveyed area shrunk by this before a "
                                            "feature counts (the pose's error places the feature; 0, 1 and 2 m were "
                                            "tried on the calibration seeds: worst MCL heading 0.053 / 0.063 / "
                                            "0.048 deg)")
    feature_deskew: bool = Field(True, description="motion-compensate each scan to its start (wheel speed + gyro) "
                                 "before extracting road features")
    feature_voxel_m: float = Field(0.1, gt=0)
    feature_window_m: float = Field(3.0, gt=0, description="moving-average window along a ring, metres of arc")
    feature_offset_sigma: float = Field(3.0, gt=0, description="threshold in robust std of the ring residual")
    feature_ground_model: Literal["level", "plane"] = Field(
        "plane", description="road surface the feature band is about: 'plane' (the scan's fitted road plane, "
        "follows roll, pitch and grade), 'level' (the mode of the near heights)")
    feature_ground_band_m: float = Field(0.15, gt=0, description="half-height of the band about the road surface "
                                         "a feature point must lie in")
    feature_max_range_m: float = Field(MARKINGS.feature_max_range_m, gt=0)
    # References
    reference_max_gap_s: float = Field(1.0, gt=0, description="no reference across gaps longer than this")
    reference_frame: str = Field("auto", description="frame of a reference trajectory file: 'auto' (the ENU "
                                 "origin its header line or NAME.frame.json sidecar states; refused when it states "
                                 "none), 'map' (already in the map's ENU frame) or 'LAT,LON,H' (ENU about that "
                                 "WGS84 origin)")
    # Coverage (issue 28): below either share the verdict is "no coverage" and the evaluation fails (exit 3)
    coverage_min_in_range: float = Field(0.5, ge=0, le=1, description="min share of epochs with a map corner "
                                         "within sensor_range_m of the GNSS/INS position")
    coverage_min_associated: float = Field(0.1, ge=0, le=1, description="min share of epochs where the EKF "
                                           "associated at least one map corner")
    # Targets (issue 28, map-relative): a verdict per target in metrics.json and the report
    target_ekf_rms_2d_m: float = Field(0.10, gt=0, description="EKF horizontal RMS (tiny: 0.15)")
    target_ekf_p99_2d_m: float = Field(0.28, gt=0)
    target_ekf_max_2d_m: float = Field(0.40, gt=0)
    target_ekf_heading_rms_deg: float = Field(0.15, gt=0)
    ekf_judge_after_startup: bool = Field(True, description="the EKF's metrics and targets count the epochs from "
                                          "its first map-corner association on (it is localized from there); the "
                                          "start-up before it is reported apart (`startup`, `all_epochs`) and "
                                          "judged by target_ekf_startup_s")
    target_ekf_startup_s: float = Field(10.0, gt=0, description="seconds from the EKF's first GNSS/INS fix to its "
                                        "first map-corner association")
    target_nees_share_below_q95: float = Field(0.95, gt=0, le=1, description="the NEES target is met when its "
                                              "mean is in the two-sided 95 % band, or above it with at least this "
                                              "share of epochs under the chi-square 0.95 quantile (3 dof); a mean "
                                              "below the band (pessimistic) never meets it")
    target_mcl_mean_abs_x_m: float = Field(0.10, gt=0)
    target_mcl_mean_abs_y_m: float = Field(0.10, gt=0)
    target_mcl_mean_abs_heading_deg: float = Field(0.15, gt=0)
    fail_on_targets: bool = Field(False, description="a missed target fails the evaluation (exit 3)")

    def evaluation_config(self) -> EvaluationConfig:
        """``evaluate_drive``'s settings (``config.EvaluationConfig``; no algorithm sees this params object)."""
        import numpy as np

        from stages.evaluate.config import EvaluationConfig

        return EvaluationConfig(ekf=self.ekf_config(), mcl=self.mcl_config(), methods=tuple(self.methods),
                                init_sigma_xy_m=self.init_sigma_xy_m,
                                init_sigma_yaw_rad=np.deg2rad(self.init_sigma_yaw_deg), ekf_motion=self.ekf_motion,
                                seed=self.seed, reference_max_gap_s=self.reference_max_gap_s,
                                ekf_judge_after_startup=self.ekf_judge_after_startup)

    def ekf_config(self) -> EkfConfig:
        """The EKF's ``localize_ekf.EkfConfig`` (angles in degrees here, radians there; gates as chi-square)."""
        import numpy as np
        from scipy.stats import chi2

        from stages.evaluate.localize_ekf import EkfConfig

        return EkfConfig(icp_sigma_frac=self.icp_sigma_frac, icp_sigma_xy_m=self.icp_sigma_xy_m,
                         icp_sigma_yaw_rad=np.deg2rad(self.icp_sigma_yaw_deg),
                         icp_sigma_yaw_frac=self.icp_sigma_yaw_frac, sensor_range_m=self.sensor_range_m,
                         gate_chi2=float(chi2.ppf(self.gate_probability, 2)),
                         angle_tol_rad=np.deg2rad(self.angle_gate_deg), association=self.association,
                         range_sigma_floor_m=self.range_sigma_floor_m,
                         bearing_sigma_floor_rad=np.deg2rad(self.bearing_sigma_floor_deg),
                         wall_heading_sigma_rad=np.deg2rad(self.wall_heading_sigma_deg),
                         map_consider=self.ekf_map_consider, map_cov_scale=self.ekf_map_cov_scale,
                         map_corr_share=self.ekf_map_corr_share, map_corr_length_m=self.ekf_map_corr_length_m,
                         gyro_bias_sigma_rad_s=np.deg2rad(self.ekf_gyro_bias_sigma_deg_s),
                         gyro_bias_rw_rad_s_per_sqrt_s=np.deg2rad(self.ekf_gyro_bias_rw_deg_s_per_sqrt_s),
                         wheel_scale_sigma=self.ekf_wheel_scale_sigma,
                         wheel_scale_rw_per_sqrt_m=self.ekf_wheel_scale_rw_per_sqrt_m,
                         wheel_sigma_frac=self.ekf_wheel_sigma_frac,
                         wheel_sigma_lateral_frac=self.ekf_wheel_sigma_lateral_frac,
                         gyro_sigma_yaw_rad=np.deg2rad(self.ekf_gyro_sigma_yaw_deg),
                         gyro_sigma_yaw_frac=self.ekf_gyro_sigma_yaw_frac,
                         icp_gate_chi2=float(chi2.ppf(self.ekf_icp_gate_probability, 3)),
                         icp_gyro_bias_state=self.ekf_icp_gyro_bias_state, icp_gyro_fusion=self.ekf_icp_gyro_fusion,
                         heading_rw_rad_per_sqrt_s=np.deg2rad(self.ekf_heading_rw_deg_per_sqrt_s),
                         icp_gyro_gate_chi2=(float(chi2.ppf(self.ekf_icp_gate_probability, 1))
                                             if self.ekf_icp_gyro_gate else 0.0),
                         markings=self.ekf_markings, marking_sharpness=self.mcl_sharpness,
                         marking_effective_points=self.mcl_effective_points,
                         marking_decorrelation_m=self.mcl_decorrelation_m,
                         corner_decorrelation_m=self.ekf_corner_decorrelation_m,
                         marking_max_features=self.mcl_max_features,
                         marking_min_info=self.ekf_marking_min_info, marking_feature_range_m=self.feature_max_range_m,
                         marking_map_sigma_m=self.ekf_marking_map_sigma_m,
                         marking_map_sigma_yaw_rad=np.deg2rad(self.ekf_marking_map_sigma_deg),
                         marking_map_length_m=self.ekf_marking_map_length_m)

    def mcl_config(self) -> MclConfig:
        """The MCL's ``localize_mcl.MclConfig`` (every mcl_* field; angles in degrees here, radians there)."""
        import numpy as np

        from stages.evaluate.localize_mcl import MclConfig

        return MclConfig(n_particles=self.n_particles, init_sigma_xy_m=self.mcl_init_sigma_xy_m,
                         init_sigma_yaw_rad=np.deg2rad(self.mcl_init_sigma_yaw_deg), sigma_frac=self.mcl_sigma_frac,
                         sigma_lateral_frac=self.mcl_sigma_lateral_frac, sigma_xy_m=self.mcl_sigma_xy_m,
                         sigma_yaw_rad=np.deg2rad(self.mcl_sigma_yaw_deg), sigma_yaw_frac=self.mcl_sigma_yaw_frac,
                         init_sigma_scale=self.mcl_init_sigma_scale,
                         sigma_scale_per_sqrt_m=self.mcl_sigma_scale_per_sqrt_m,
                         init_sigma_gyro_bias_radps=np.deg2rad(self.mcl_init_sigma_gyro_bias_deg_s),
                         sigma_gyro_bias_per_sqrt_s=np.deg2rad(self.mcl_sigma_gyro_bias_deg_s_per_sqrt_s),
                         init_sigma_gyro_gain=self.mcl_init_sigma_gyro_gain,
                         decorrelation_m=self.mcl_decorrelation_m, sharpness=self.mcl_sharpness,
                         effective_points=self.mcl_effective_points, max_features=self.mcl_max_features,
                         max_inject=self.mcl_max_inject, inject_sigma_xy_m=self.mcl_inject_sigma_xy_m,
                         feature_range_m=self.feature_max_range_m)

    def coverage_margin_m(self) -> float | None:
        """The marking windows' coverage margin (``map_access.map_inputs``), None when coverage is off."""
        return self.raster_coverage_margin_m if self.raster_coverage else None

    def field_config(self) -> FieldConfig:
        """The marking likelihood field's ``config.FieldConfig``."""
        from stages.evaluate.config import FieldConfig

        return FieldConfig(kind=self.raster_field, sigma_m=self.raster_sigma_m, blur_m=self.raster_blur_m)

    def target_config(self) -> TargetConfig:
        """The verdict's ``config.TargetConfig``: per method, metric key -> upper limit."""
        from stages.evaluate.config import TargetConfig

        return TargetConfig(
            limits={"ekf": {"rms_2d_m": self.target_ekf_rms_2d_m, "p99_2d_m": self.target_ekf_p99_2d_m,
                            "max_2d_m": self.target_ekf_max_2d_m,
                            "heading_rms_deg": self.target_ekf_heading_rms_deg,
                            **({"startup_s": self.target_ekf_startup_s} if self.ekf_judge_after_startup else {})},
                    "mcl": {"mean_abs_x_m": self.target_mcl_mean_abs_x_m,
                            "mean_abs_y_m": self.target_mcl_mean_abs_y_m,
                            "mean_abs_heading_deg": self.target_mcl_mean_abs_heading_deg}},
            min_nees_share_below_q95=self.target_nees_share_below_q95)

    @model_validator(mode="after")
    def _methods(self) -> "EvaluateParams":
        if not self.methods:
            raise ValueError("methods: name at least one of 'ekf', 'mcl'")
        parse_reference_frame(self.reference_frame)
        return self


def parse_reference_frame(value: str):
    """'auto' | 'map' | an EnuOrigin from 'LAT,LON,H' (ValueError otherwise)."""
    if value in ("auto", "map"):
        return value
    from stages.common.geodesy import EnuOrigin, OriginError

    try:
        return EnuOrigin.parse(value)
    except OriginError as exc:
        raise ValueError(f"reference_frame: expected 'auto', 'map' or 'LAT,LON,H'; {exc}") from None
