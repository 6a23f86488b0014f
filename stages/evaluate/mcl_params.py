"""The marking MCL's section of the evaluate params (Kim, Liu & Myung s.2.3), ``evaluate.mcl``, the object
``localize_mcl.run_mcl`` receives, and the road-marking likelihood both filters share, ``evaluate.markings``.
Angles are stated in degrees; the filter reads radians through the properties ending in ``_rad`` / ``_radps``.

The MCL predicts with wheel speed + gyro through a per-particle wheel scale, gyro bias and gyro gain; weighs the
particles by the correlation of each scan's road features with a distance likelihood field of the map's marking
raster, tempered by the travel since the previous scan; resamples (low variance) with progressive correction and
roughening; and, when the scans stop fitting, may inject candidates about the estimate (guarded Augmented MCL).
Defaults the tiles stage's localizability prediction shares come from ``stages.common.localizer_defaults``.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.declare import Params
from stages.common.localizer_defaults import MARKINGS, MCL_MOTION


class MarkingLikelihood(Params):
    """The road markings' likelihood, shared by the MCL and the EKF's marking update: log-likelihood = alpha *
    sharpness * min(F, effective_points) * correlation of the scan's F features with the likelihood field, alpha =
    min(1, travel since the scan last counted / decorrelation_m)."""

    field: Literal["distance", "blur"] = Field("distance", description="likelihood field of a marking window: "
                                               "exp(-d^2/2 sigma^2) of the distance to paint, or a blurred mask")
    sigma_m: float = Field(MARKINGS.raster_sigma_m, gt=0, description="sigma of the distance likelihood field")
    blur_m: float = Field(0.2, ge=0, description="Gaussian blur of the marking raster (field=blur)")
    coverage: bool = Field(True, description="count only the road features that fall where the map saw the ground "
                           "(its point_count layer; beyond the survey 'no paint' is not known)")
    coverage_margin_m: float = Field(2.0, ge=0, description="the surveyed area shrunk by this before a feature "
                                     "counts (the pose's error places the feature)")
    sharpness: float = Field(MARKINGS.sharpness, gt=0, description="log-likelihood gain per effective feature point")
    effective_points: float = Field(MARKINGS.effective_points, gt=0, description="feature points that count at most")
    decorrelation_m: float = Field(MARKINGS.decorrelation_m, ge=0,
                                   description="travel after which a scan counts fully (0 = always)")
    max_features: int = Field(400, ge=10, description="features of a scan used at most (drawn at random)")
    feature_range_m: float = Field(MARKINGS.feature_max_range_m, gt=0,
                                   description="road features farther than this are not extracted nor used")

    def coverage_margin(self) -> float | None:
        """The marking windows' coverage margin (``map_access.map_inputs``), None when coverage is off."""
        return self.coverage_margin_m if self.coverage else None


class MclRecovery(Params):
    """Guarded Augmented MCL (Thrun et al. Table 8.3): candidates about the estimate replace a share of the
    particles when the scans fit much worse than they used to, and only when the best candidate fits well."""

    score_fast: float = Field(0.2, gt=0, le=1, description="smoothing of the short-term mean correlation score")
    score_slow: float = Field(0.01, gt=0, le=1, description="smoothing of the long-term one")
    inject_ratio: float = Field(0.8, gt=0, description="candidates are drawn while short-term / long-term falls "
                                "below this")
    max_inject: float = Field(0.3, ge=0, le=1, description="share of particles a recovery may replace; 0 = off")
    inject_margin: float = Field(0.2, ge=0, description="a candidate must beat every particle by this share of the "
                                 "long-term score")
    inject_sigma_xy_m: float = Field(1.0, gt=0, description="spread of recovery candidates about the estimate")
    inject_sigma_yaw_deg: float = Field(1.0, gt=0, description="their heading spread")

    @property
    def inject_sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.inject_sigma_yaw_deg)


class MclConfig(Params):
    """The marking MCL: particles, motion noise on top of each particle's calibration (wheel scale, gyro bias,
    gyro gain), resampling and the recovery section."""

    n_particles: int = Field(1000, ge=10)
    seed: int = Field(0, description="seed of the filter's random draws")
    init_sigma_xy_m: float = Field(MCL_MOTION.init_sigma_xy_m, gt=0, description="initial position spread")
    init_sigma_yaw_deg: float = Field(MCL_MOTION.init_sigma_yaw_deg, gt=0, description="initial heading spread")
    sigma_frac: float = Field(MCL_MOTION.sigma_frac, ge=0,
                              description="along-track motion noise per metre (beside the scale)")
    sigma_lateral_frac: float = Field(MCL_MOTION.sigma_lateral_frac, ge=0,
                                      description="across-track motion noise per metre")
    sigma_xy_m: float = Field(MCL_MOTION.sigma_xy_m, ge=0, description="translation motion noise floor per moving "
                              "scan")
    sigma_yaw_deg: float = Field(MCL_MOTION.sigma_yaw_deg, ge=0,
                                 description="heading motion noise per moving scan (beside the bias)")
    sigma_yaw_frac: float = Field(0.01, ge=0, description="heading motion noise per radian turned")
    init_sigma_scale: float = Field(0.01, ge=0, description="wheel-speed scale std per particle (0 = no state)")
    sigma_scale_per_sqrt_m: float = Field(1e-3, ge=0, description="random walk of the wheel scale")
    init_sigma_gyro_bias_deg_s: float = Field(0.115, ge=0, description="gyro bias std per particle, deg/s")
    sigma_gyro_bias_deg_s_per_sqrt_s: float = Field(0.0057, ge=0, description="random walk of the gyro bias")
    init_sigma_gyro_gain: float = Field(0.005, ge=0, description="gyro gain (scale factor) std about 1 per particle "
                                        "(0 = not a state): a turn's heading error is the gain's, systematic over "
                                        "the drive")
    epoch_s: float = Field(0.1, gt=0, description="scan period, used when the epoch stamps are not given")
    standstill_m: float = Field(1e-3, ge=0, description="a step shorter than this is a standstill: pose held, no "
                                "update")
    min_features: int = Field(10, ge=1, description="a scan with fewer features does not update")
    resample_neff_ratio: float = Field(0.5, gt=0, le=1, description="resample when the effective sample size falls "
                                       "below this share of the particles")
    min_ess_ratio: float = Field(0.05, gt=0, le=1, description="an update that would leave fewer effective "
                                 "particles is applied in pieces (progressive correction)")
    max_corrections: int = Field(6, ge=1, description="pieces of one update at most")
    roughen_xy_m: float = Field(0.005, ge=0, description="roughening of the resampled positions")
    roughen_yaw_deg: float = Field(0.005, ge=0, description="roughening of the resampled headings")
    window_m: float = Field(240.0, gt=0, description="side of a fetched raster window")
    recovery: MclRecovery = MclRecovery()

    @property
    def init_sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.init_sigma_yaw_deg)

    @property
    def sigma_yaw_rad(self) -> float:
        return np.deg2rad(self.sigma_yaw_deg)

    @property
    def init_sigma_gyro_bias_radps(self) -> float:
        return np.deg2rad(self.init_sigma_gyro_bias_deg_s)

    @property
    def sigma_gyro_bias_rad_s_per_sqrt_s(self) -> float:
        return np.deg2rad(self.sigma_gyro_bias_deg_s_per_sqrt_s)

    @property
    def roughen_yaw_rad(self) -> float:
        return np.deg2rad(self.roughen_yaw_deg)
