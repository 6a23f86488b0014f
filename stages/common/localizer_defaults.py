"""The localizers' measurement and motion noise, stated once.

The evaluate stage's params sections (``stages/evaluate/ekf_params.py``, ``mcl_params.py``) take their defaults
from here, and the tiles stage's localizability layer (``stages/common/localizability.py``) predicts with the same
values, so a prediction follows the filters it predicts: change a default here and both move (each stage's code
digest follows this module).
Units in the names; angles in degrees as the params state them.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CornerEkfNoise:
    """The corner EKF's (Im et al. 2016 s.4) noise: the defaults of ``evaluate``'s ``ekf`` section."""

    sensor_range_m: float = 60.0  # map corners farther than this are not predicted
    # added to an extracted corner's range / bearing variance: the extraction's own scatter per look (0.027-0.031 m,
    # 0.05-0.11 deg on the calibration seeds; docs/evaluation.md "Consistency of the corner EKF (NEES)"). Was 0.05 m /
    # 0.15 deg, which with the ICP heading noise held make demo's NEES at 1.89 (pessimistic).
    range_sigma_floor_m: float = 0.03
    bearing_sigma_floor_deg: float = 0.08
    wall_heading_sigma_deg: float = 1.5  # heading measured from each wall direction
    corner_decorrelation_m: float = 0.5  # a look counts fully after this much travel since the corner's last one
    # ICP translation std per scan: icp_sigma_xy_m + icp_sigma_frac x metres travelled. The consecutive edges' error
    # against the simulator's truth is about 0.003-0.01 m per scan whatever the step (demo 201: along 0.003 / 0.0045 /
    # 0.0087 m at 0-0.05 / 0.3-0.6 / 0.6-0.9 m steps, across 0.003; tiny 201-203: along 0.009-0.010, across 0.006 at
    # 0.41 m), white over 100 scans. Was 0.03 / 0.01 (2.5-4x that).
    icp_sigma_frac: float = 0.01
    icp_sigma_xy_m: float = 0.005
    icp_sigma_yaw_deg: float = 0.016  # ICP heading std per scan
    map_corr_share: float = 0.0  # two map corners' errors correlate share * exp(-d^2 / 2 L^2) (map states none)
    map_corr_length_m: float = 50.0
    init_sigma_xy_m: float = 0.7  # floor of the initial position std
    init_sigma_yaw_deg: float = 0.5


@dataclass(frozen=True)
class MarkingNoise:
    """The road-marking likelihood shared by the MCL and the EKF's marking update (Kim, Liu & Myung s.2.3)."""

    raster_sigma_m: float = 0.2  # sigma of the distance likelihood field exp(-d^2 / 2 sigma^2)
    sharpness: float = 5.0  # log-likelihood gain per effective feature point
    effective_points: float = 60.0  # feature points that count at most
    decorrelation_m: float = 0.5  # travel after which a scan counts fully
    feature_max_range_m: float = 30.0  # road features farther than this are not used
    map_sigma_m: float = 0.036  # the raster's own local error per axis (a Gauss-Markov offset along the road)
    map_sigma_deg: float = 0.092  # its heading part
    map_length_m: float = 50.0  # its correlation length along the road


@dataclass(frozen=True)
class MclMotionNoise:
    """The MCL's wheel/gyro motion noise (its per-particle scale and bias aside)."""

    sigma_frac: float = 0.005  # along-track per metre
    sigma_lateral_frac: float = 0.002  # across-track per metre
    sigma_xy_m: float = 0.02  # floor per moving scan
    sigma_yaw_deg: float = 0.03  # heading per moving scan
    init_sigma_xy_m: float = 1.0
    init_sigma_yaw_deg: float = 1.0


CORNER_EKF = CornerEkfNoise()
MARKINGS = MarkingNoise()
MCL_MOTION = MclMotionNoise()
