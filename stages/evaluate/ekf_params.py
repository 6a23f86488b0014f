"""The corner EKF's section of the evaluate params (Im et al. 2016 s.4): ``evaluate.ekf`` and its sub-sections, the
object ``localize_ekf.run_ekf`` receives. Angles are stated in degrees and gates as probabilities; the filter reads
the radian and chi-square values through the properties of the same name ending in ``_rad`` / ``_chi2``.

Defaults the tiles stage's localizability prediction shares come from ``stages.common.localizer_defaults``.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.declare import Params
from stages.common.localizer_defaults import CORNER_EKF, MARKINGS


@lru_cache(maxsize=64)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile of a gate (``scipy.stats.chi2.ppf``), computed once per value."""
    from scipy.stats import chi2

    return float(chi2.ppf(probability, dof))


class EkfIcpMotion(Params):
    """The ICP motion model (``ekf.motion: icp``, eq. 2): each scan's ICP increment, the wheel/gyro increment where
    ICP failed or disagrees with the gyro, and the gyro bias as a 4th state carried by those fallback increments."""

    sigma_frac: float = Field(CORNER_EKF.icp_sigma_frac, ge=0, description="ICP translation std per metre travelled")
    sigma_xy_m: float = Field(CORNER_EKF.icp_sigma_xy_m, ge=0, description="ICP translation std floor per scan")
    sigma_yaw_deg: float = Field(CORNER_EKF.icp_sigma_yaw_deg, ge=0, description="ICP heading std per scan where "
                                 "the registration states none (or registration_yaw_scale is 0)")
    registration_yaw_scale: float = Field(2.7, ge=0, description="each scan's ICP heading std is this times the "
                                          "registration's own stated std (the planar marginal of the edge's "
                                          "information, odometry's point-to-plane Hessian, its floor taken out); "
                                          "0: sigma_yaw_deg for every scan")
    registration_yaw_floor_deg: float = Field(float(np.degrees(1e-4)), ge=0,
                                              description="the floor odometry adds to every edge's rotation "
                                              "std (its information.min_sigma_rad, 1e-4 rad = 0.00573 deg), "
                                              "taken out of the stated heading variance before the scale: "
                                              "not the scene's")
    sigma_yaw_frac: float = Field(0.0, ge=0, description="ICP heading std per radian turned (0: turns no worse)")
    wheel_gate_deg: float = Field(0.05, ge=0, description="an ICP increment whose heading change differs from the "
                                  "wheel/gyro increment's by more than this is replaced by the wheel/gyro increment, "
                                  "as a failed one is (0 = failed edges only)")
    gate_probability: float = Field(0.999, gt=0, lt=1, description="ICP increment vs wheel/gyro consistency gate "
                                    "(chi-square, 3 dof for wheel_bias, 1 dof for gyro_gate)")
    gyro_bias_state: bool = Field(True, description="the gyro bias as a 4th state, carried by the wheel/gyro "
                                  "fallback increments (their heading std grows with the time spent on them)")
    gyro_fusion: bool = Field(True, description="with gyro_bias_state: the gyro's heading change also measures each "
                              "accepted ICP increment's (estimates the bias while ICP holds)")
    gyro_gate: bool = Field(True, description="with the fusion: ICP is gated against the bias-corrected gyro with "
                            "the innovation's variance (chi-square 1 dof at gate_probability) instead of "
                            "wheel_gate_deg")
    heading_rw_deg_per_sqrt_s: float = Field(0.0, ge=0, description="heading random walk beside sigma_yaw_deg")

    @property
    def sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.sigma_yaw_deg)

    @property
    def registration_yaw_floor_rad(self) -> float:
        return np.deg2rad(self.registration_yaw_floor_deg)

    @property
    def heading_rw_rad_per_sqrt_s(self) -> float:
        return np.deg2rad(self.heading_rw_deg_per_sqrt_s)

    @property
    def gate_chi2(self) -> float:
        """The wheel_bias model's ICP vs wheel/gyro gate (3 dof)."""
        return chi2_quantile(self.gate_probability, 3)

    @property
    def gyro_gate_chi2(self) -> float:
        """The ICP vs bias-corrected gyro gate (1 dof); 0 = off."""
        return chi2_quantile(self.gate_probability, 1) if self.gyro_gate else 0.0


class EkfWheelMotion(Params):
    """The wheel/gyro increments' noise (the ``wheel_bias`` motion model and the ICP model's fallback increments),
    and the gyro bias and wheel scale states."""

    gyro_bias_sigma_deg_s: float = Field(0.115, gt=0, description="initial gyro bias std (MEMS spec, as the MCL)")
    gyro_bias_rw_deg_s_per_sqrt_s: float = Field(0.0057, ge=0, description="gyro bias random walk")
    scale_sigma: float = Field(0.01, gt=0, description="initial wheel-speed scale error std")
    scale_rw_per_sqrt_m: float = Field(1e-3, ge=0, description="wheel scale random walk")
    sigma_frac: float = Field(0.005, ge=0, description="wheel along-track noise per metre")
    sigma_lateral_frac: float = Field(0.002, ge=0, description="wheel across-track (slip) noise per metre")
    sigma_xy_m: float = Field(0.005, ge=0, description="wheel translation noise floor per scan")
    gyro_sigma_yaw_deg: float = Field(0.01, ge=0, description="gyro heading noise per scan (beside the bias)")
    gyro_sigma_yaw_frac: float = Field(0.005, ge=0, description="gyro scale error per radian turned")

    @property
    def gyro_bias_sigma_rad_s(self) -> float:
        return np.deg2rad(self.gyro_bias_sigma_deg_s)

    @property
    def gyro_bias_rw_rad_s_per_sqrt_s(self) -> float:
        return np.deg2rad(self.gyro_bias_rw_deg_s_per_sqrt_s)

    @property
    def gyro_sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.gyro_sigma_yaw_deg)


class EkfCorners(Params):
    """Association and measurement of the map corners (s.3.3, eqs. 3-5)."""

    sensor_range_m: float = Field(CORNER_EKF.sensor_range_m, gt=0,
                                  description="map corners farther than this are not predicted")
    gate_probability: float = Field(0.99, gt=0, lt=1, description="Mahalanobis gate, chi-square 2 dof")
    angle_gate_deg: float = Field(15.0, gt=0, le=180, description="max wall direction difference")
    association: Literal["gnn", "nn"] = Field("gnn", description="global nearest neighbour or nearest neighbour")
    range_sigma_floor_m: float = Field(CORNER_EKF.range_sigma_floor_m, ge=0,
                                       description="added to extracted corners' range std")
    bearing_sigma_floor_deg: float = Field(CORNER_EKF.bearing_sigma_floor_deg, ge=0,
                                           description="added to extracted corners' bearing std")
    startup_range_sigma_floor_m: float = Field(0.05, ge=0, description="the range floor (at least) until the "
                                               "filter's first corner update: from a GNSS fix metres off, its "
                                               "linearisation errs beyond the extraction's scatter")
    startup_bearing_sigma_floor_deg: float = Field(0.15, ge=0, description="the bearing floor (at least) until the "
                                                   "first corner update")
    wall_heading_sigma_deg: float = Field(CORNER_EKF.wall_heading_sigma_deg, ge=0,
                                          description="heading from wall directions; 0 = off (range/bearing only)")
    decorrelation_m: float = Field(CORNER_EKF.corner_decorrelation_m, ge=0,
                                   description="a corner's range/bearing and wall-heading noise is divided by "
                                   "min(1, travel since the corner last measured the pose / this): looks from nearly "
                                   "the same place repeat most of the extraction error (0 = every look counts fully)")

    @property
    def gate_chi2(self) -> float:
        return chi2_quantile(self.gate_probability, 2)

    @property
    def angle_tol_rad(self) -> float:
        return np.deg2rad(self.angle_gate_deg)

    @property
    def bearing_sigma_floor_rad(self) -> float:
        return np.deg2rad(self.bearing_sigma_floor_deg)

    @property
    def startup_bearing_sigma_floor_rad(self) -> float:
        return np.deg2rad(self.startup_bearing_sigma_floor_deg)

    @property
    def wall_heading_sigma_rad(self) -> float:
        return np.deg2rad(self.wall_heading_sigma_deg)


class EkfMapErrors(Params):
    """The map corners' own errors (``consider``): Schmidt consider states shared by every epoch that uses a corner,
    not fresh noise at each, correlated between corners at distance d as share * exp(-d^2 / (2 L^2))."""

    consider: bool = Field(True, description="map-corner errors as consider states (False: the paper's R only)")
    consider_forget_m: float = Field(120.0, gt=0, description="a corner farther than this leaves the consider set")
    cov_scale: float = Field(1.0, gt=0, description="multiplies the map's stored corner covariances")
    corr_share: float = Field(CORNER_EKF.map_corr_share, ge=0, lt=1, description="correlation share of two map "
                              "corners' errors (corners seen from one stretch of the survey drive share its pose "
                              "error)")
    corr_length_m: float = Field(CORNER_EKF.map_corr_length_m, gt=0, description="length L of that correlation")
    corr_source: Literal["map", "params"] = Field(
        "map", description="map: the correlation the published map states (its pose graph's joint marginals, "
        "manifest corner_error_correlation) replaces corr_share / corr_length_m when it states one; params: those "
        "two values always")


class EkfMarkings(Params):
    """The road-marking update: each scan's road features measure the pose against the map's marking raster with
    the MCL's likelihood (``evaluate.markings``), along the directions they inform (the lateral position and the
    heading between corners; ``ekf_markings.py``)."""

    enabled: bool = Field(True, description="the road-marking update is on")
    min_info: float = Field(0.05, gt=0, description="a direction the markings inform less than this share of the "
                            "prior's information is not measured")
    min_features: int = Field(10, ge=1, description="a scan with fewer features in the window measures nothing")
    gate_probability: float = Field(0.999, gt=0, lt=1, description="innovation gate (chi-square, as many dof as "
                                    "directions measured)")
    grid_n: int = Field(7, ge=3, description="likelihood grid points per axis about the prediction")
    window_m: float = Field(240.0, gt=0, description="side of a fetched raster window")
    map_sigma_m: float = Field(MARKINGS.map_sigma_m, ge=0, description="the marking raster's own local error per "
                               "axis (a Gauss-Markov offset along the road, a consider parameter; the map's stated "
                               "relative pose error replaces it)")
    map_sigma_deg: float = Field(MARKINGS.map_sigma_deg, ge=0, description="its heading part")
    map_length_m: float = Field(MARKINGS.map_length_m, gt=0, description="its correlation length along the road")

    @property
    def map_sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.map_sigma_deg)


class EkfConfig(Params):
    """The corner EKF: its start, its motion model and the sections above. ``motion``: 'icp' (the paper's ICP
    increments, the wheel/gyro fallback and the gyro gate) or 'wheel_bias' (the wheel/gyro increment is the motion
    prior, the ICP increment measures it when consistent, the gyro bias and wheel scale are states)."""

    motion: Literal["wheel_bias", "icp"] = Field("icp", description="EKF motion model")
    # the first GNSS/INS fix, its reported std floored by these (urban RTK/INS understates its error in canyons)
    init_sigma_xy_m: float = Field(CORNER_EKF.init_sigma_xy_m, gt=0, description="floor of the initial position std")
    init_sigma_yaw_deg: float = Field(CORNER_EKF.init_sigma_yaw_deg, gt=0,
                                      description="floor of the initial heading std")
    judge_after_startup: bool = Field(True, description="the EKF's metrics and targets count the epochs from its "
                                      "first map-corner association on (it is localized from there); the start-up "
                                      "before it is reported apart (`startup`, `all_epochs`) and judged by "
                                      "targets.ekf_startup_s")
    icp: EkfIcpMotion = EkfIcpMotion()
    wheel: EkfWheelMotion = EkfWheelMotion()
    corners: EkfCorners = EkfCorners()
    map: EkfMapErrors = EkfMapErrors()
    markings: EkfMarkings = EkfMarkings()

    @property
    def init_sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.init_sigma_yaw_deg)

    def replace(self, **sections: dict) -> "EkfConfig":
        """A copy with some fields of some sections changed: ``cfg.replace(markings={"enabled": False})``."""
        return self.model_copy(update={name: getattr(self, name).model_copy(update=values)
                                       for name, values in sections.items()})
