"""Parameters of the evaluate stage, in sections that are what the algorithms receive: ``ekf`` (the corner EKF, Im et
al. s.4; ``ekf_params.EkfConfig``), ``mcl`` (the marking MCL, Kim et al. s.2.3; ``mcl_params.MclConfig``),
``markings`` (the road markings' likelihood both filters use), ``features`` (road feature extraction),
``reference``, ``coverage`` and ``targets`` (the verdict)."""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from pipeline.declare import Params
from stages.evaluate.ekf_params import EkfConfig
from stages.evaluate.mcl_params import MarkingLikelihood, MclConfig


def parse_reference_frame(value: str):
    """'auto' | 'map' | an EnuOrigin from 'LAT,LON,H' (ValueError otherwise)."""
    if value in ("auto", "map"):
        return value
    from stages.common.geodesy import EnuOrigin, OriginError

    try:
        return EnuOrigin.parse(value)
    except OriginError as exc:
        raise ValueError(f"reference_frame: expected 'auto', 'map' or 'LAT,LON,H'; {exc}") from None


class FeatureParams(Params):
    """Road features of each scan (``stages.common.road_features.extract_road_features``); their range is
    ``markings.feature_range_m``."""

    deskew: bool = Field(True, description="motion-compensate each scan to its start (wheel speed + gyro) before "
                         "extracting road features")
    voxel_m: float = Field(0.1, gt=0, description="voxel size the scan is thinned to")
    window_m: float = Field(3.0, gt=0, description="moving-average window along a ring, metres of arc")
    offset_sigma: float = Field(3.0, gt=0, description="threshold in robust std of the ring residual")
    ground_model: Literal["level", "plane"] = Field(
        "plane", description="road surface the feature band is about: 'plane' (the scan's fitted road plane, "
        "follows roll, pitch and grade), 'level' (the mode of the near heights)")
    ground_band_m: float = Field(0.15, gt=0, description="half-height of the band about the road surface a feature "
                                 "point must lie in")


class ReferenceParams(Params):
    """The reference trajectories the localizers are scored against."""

    max_gap_s: float = Field(1.0, gt=0, description="no reference across gaps longer than this")
    frame: str = Field("auto", description="frame of a reference trajectory file: 'auto' (the ENU origin its header "
                       "line or NAME.frame.json sidecar states; refused when it states none), 'map' (already in the "
                       "map's ENU frame) or 'LAT,LON,H' (ENU about that WGS84 origin)")

    @model_validator(mode="after")
    def _frame(self) -> "ReferenceParams":
        parse_reference_frame(self.frame)
        return self


class CoverageParams(Params):
    """Below either share the verdict is "no coverage" and the evaluation fails (exit 3)."""

    min_in_range: float = Field(0.5, ge=0, le=1, description="min share of epochs with a map corner within "
                                "ekf.corners.sensor_range_m of the GNSS/INS position")
    min_associated: float = Field(0.1, ge=0, le=1, description="min share of epochs where the EKF associated at "
                                  "least one map corner")


class TargetConfig(Params):
    """The verdict's targets (map-relative): per method, a metric's upper limit, a verdict per target in
    metrics.json and the report."""

    ekf_rms_2d_m: float = Field(0.10, gt=0, description="EKF horizontal RMS")
    ekf_p99_2d_m: float = Field(0.28, gt=0, description="EKF horizontal 99th percentile")
    ekf_max_2d_m: float = Field(0.40, gt=0, description="EKF horizontal maximum")
    ekf_heading_rms_deg: float = Field(0.15, gt=0, description="EKF heading RMS")
    ekf_judge_after_startup: bool = Field(True, description="the EKF's metrics and targets count the epochs from its "
                                          "first map-corner association on (it is localized from there); the "
                                          "start-up before it is reported apart (`startup`, `all_epochs`) and judged "
                                          "by ekf_startup_s")
    ekf_startup_s: float = Field(10.0, gt=0, description="seconds from the EKF's first GNSS/INS fix to its first "
                                 "map-corner association")
    nees_share_below_q95: float = Field(0.95, gt=0, le=1, description="the NEES target is met when its mean is in "
                                        "the two-sided 95 % band, or above it with at least this share of epochs "
                                        "under the chi-square 0.95 quantile (3 dof); a mean below the band "
                                        "(pessimistic) never meets it")
    mcl_mean_abs_x_m: float = Field(0.10, gt=0, description="MCL mean absolute along-track error")
    mcl_mean_abs_y_m: float = Field(0.10, gt=0, description="MCL mean absolute across-track error")
    mcl_mean_abs_heading_deg: float = Field(0.15, gt=0, description="MCL mean absolute heading error")

    @property
    def limits(self) -> dict[str, dict[str, float]]:
        """Per method, metric key -> upper limit."""
        return {"ekf": {"rms_2d_m": self.ekf_rms_2d_m, "p99_2d_m": self.ekf_p99_2d_m, "max_2d_m": self.ekf_max_2d_m,
                        "heading_rms_deg": self.ekf_heading_rms_deg,
                        **({"startup_s": self.ekf_startup_s} if self.ekf_judge_after_startup else {})},
                "mcl": {"mean_abs_x_m": self.mcl_mean_abs_x_m, "mean_abs_y_m": self.mcl_mean_abs_y_m,
                        "mean_abs_heading_deg": self.mcl_mean_abs_heading_deg}}


class EvaluateParams(Params):
    """The evaluate stage's params; also ``run.evaluate_drive``'s settings."""

    renamed: ClassVar = {}  # filled below: every flat key of the earlier params -> its place now

    methods: list[Literal["ekf", "mcl"]] = Field(["ekf", "mcl"], description="localizers; baselines always run")
    fail_on_targets: bool = Field(False, description="a missed target fails the evaluation (exit 3)")
    ekf: EkfConfig = EkfConfig()
    mcl: MclConfig = MclConfig()
    markings: MarkingLikelihood = MarkingLikelihood()
    features: FeatureParams = FeatureParams()
    reference: ReferenceParams = ReferenceParams()
    coverage: CoverageParams = CoverageParams()
    targets: TargetConfig = TargetConfig()

    @model_validator(mode="after")
    def _methods(self) -> "EvaluateParams":
        if not self.methods:
            raise ValueError("methods: name at least one of 'ekf', 'mcl'")
        return self


EvaluateParams.renamed = {
    "init_sigma_xy_m": "ekf.init_sigma_xy_m", "init_sigma_yaw_deg": "ekf.init_sigma_yaw_deg",
    "ekf_motion": "ekf.motion", "ekf_judge_after_startup": "targets.ekf_judge_after_startup",
    **{f"icp_{k}": f"ekf.icp.{k}" for k in ("sigma_frac", "sigma_xy_m", "sigma_yaw_deg", "sigma_yaw_frac",
                                            "wheel_gate_deg")},
    "ekf_icp_gate_probability": "ekf.icp.gate_probability", "ekf_icp_gyro_bias_state": "ekf.icp.gyro_bias_state",
    "ekf_icp_gyro_fusion": "ekf.icp.gyro_fusion", "ekf_icp_gyro_gate": "ekf.icp.gyro_gate",
    "ekf_heading_rw_deg_per_sqrt_s": "ekf.icp.heading_rw_deg_per_sqrt_s",
    **{f"ekf_{k}": f"ekf.wheel.{k}" for k in ("gyro_bias_sigma_deg_s", "gyro_bias_rw_deg_s_per_sqrt_s",
                                              "gyro_sigma_yaw_deg", "gyro_sigma_yaw_frac")},
    "ekf_wheel_scale_sigma": "ekf.wheel.scale_sigma", "ekf_wheel_scale_rw_per_sqrt_m": "ekf.wheel.scale_rw_per_sqrt_m",
    "ekf_wheel_sigma_frac": "ekf.wheel.sigma_frac", "ekf_wheel_sigma_lateral_frac": "ekf.wheel.sigma_lateral_frac",
    **{k: f"ekf.corners.{k}" for k in ("sensor_range_m", "gate_probability", "angle_gate_deg", "association",
                                       "range_sigma_floor_m", "bearing_sigma_floor_deg", "wall_heading_sigma_deg")},
    "ekf_corner_decorrelation_m": "ekf.corners.decorrelation_m",
    "ekf_map_consider": "ekf.map.consider", "ekf_map_cov_scale": "ekf.map.cov_scale",
    "ekf_map_corr_share": "ekf.map.corr_share", "ekf_map_corr_length_m": "ekf.map.corr_length_m",
    "ekf_map_corr_source": "ekf.map.corr_source",
    "ekf_markings": "ekf.markings.enabled", "ekf_marking_min_info": "ekf.markings.min_info",
    "ekf_marking_map_sigma_m": "ekf.markings.map_sigma_m", "ekf_marking_map_sigma_deg": "ekf.markings.map_sigma_deg",
    "ekf_marking_map_length_m": "ekf.markings.map_length_m",
    "n_particles": "mcl.n_particles", "seed": "mcl.seed",
    **{f"mcl_{k}": f"mcl.{k}" for k in (
        "init_sigma_xy_m", "init_sigma_yaw_deg", "sigma_frac", "sigma_lateral_frac", "sigma_xy_m", "sigma_yaw_deg",
        "sigma_yaw_frac", "init_sigma_scale", "sigma_scale_per_sqrt_m", "init_sigma_gyro_bias_deg_s",
        "sigma_gyro_bias_deg_s_per_sqrt_s", "init_sigma_gyro_gain")},
    "mcl_max_inject": "mcl.recovery.max_inject", "mcl_inject_sigma_xy_m": "mcl.recovery.inject_sigma_xy_m",
    **{f"mcl_{k}": f"markings.{k}" for k in ("decorrelation_m", "sharpness", "effective_points", "max_features")},
    "raster_field": "markings.field", "raster_sigma_m": "markings.sigma_m", "raster_blur_m": "markings.blur_m",
    "raster_coverage": "markings.coverage", "raster_coverage_margin_m": "markings.coverage_margin_m",
    "feature_max_range_m": "markings.feature_range_m",
    **{f"feature_{k}": f"features.{k}" for k in ("deskew", "voxel_m", "window_m", "offset_sigma", "ground_model",
                                                 "ground_band_m")},
    "reference_max_gap_s": "reference.max_gap_s", "reference_frame": "reference.frame",
    "coverage_min_in_range": "coverage.min_in_range", "coverage_min_associated": "coverage.min_associated",
    **{f"target_{k}": f"targets.{k}" for k in (
        "ekf_rms_2d_m", "ekf_p99_2d_m", "ekf_max_2d_m", "ekf_heading_rms_deg", "ekf_startup_s",
        "nees_share_below_q95", "mcl_mean_abs_x_m", "mcl_mean_abs_y_m", "mcl_mean_abs_heading_deg")},
}
