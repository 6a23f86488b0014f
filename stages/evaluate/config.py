"""The evaluation's settings in sections, built from the stage's params by ``EvaluateParams`` methods
(``evaluation_config``, ``field_config``, ``target_config``); tests and benches build them directly.

The EKF's and the MCL's own sections are ``localize_ekf.EkfConfig`` and ``localize_mcl.MclConfig``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.evaluate.localize_ekf import EkfConfig
from stages.evaluate.localize_mcl import MclConfig


@dataclass(frozen=True)
class FieldConfig:
    """The MCL's likelihood field of a marking window: ``kind`` 'distance' (exp(-d^2 / 2 sigma_m^2) of the
    distance to paint) or 'blur' (the marking mask blurred by a Gaussian of ``blur_m``)."""

    kind: str = "distance"
    sigma_m: float = 0.2
    blur_m: float = 0.2


@dataclass(frozen=True)
class EvaluationConfig:
    """``evaluate_drive``'s settings: the localizers to run (the baselines always run), the floors of the EKF's
    initial std, its motion model ('icp' or 'wheel_bias'), the two filters' sections, the MCL's random seed,
    the longest gap a reference is interpolated across, and whether the EKF is scored from its first map-corner
    association on (its start-up reported apart)."""

    ekf: EkfConfig = field(default_factory=EkfConfig)
    mcl: MclConfig = field(default_factory=MclConfig)
    methods: tuple[str, ...] = ("ekf", "mcl")
    init_sigma_xy_m: float = 0.7
    init_sigma_yaw_rad: float = np.deg2rad(0.5)
    ekf_motion: str = "icp"
    seed: int = 0
    reference_max_gap_s: float = 1.0
    ekf_judge_after_startup: bool = True


@dataclass(frozen=True)
class TargetConfig:
    """The verdict's targets: per method, metric key -> upper limit; and the share of epochs under the
    chi-square 0.95 quantile that makes the EKF's NEES consistent when its mean is outside the 95 % band."""

    limits: dict[str, dict[str, float]]
    min_nees_share_below_q95: float = 0.95
