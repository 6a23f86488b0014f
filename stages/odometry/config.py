"""The odometry algorithm's settings in sections, one per step of ``estimate_edges``. Each section is a frozen
``Params`` holding its defaults (written here only); ``OdometryParams`` (params.py) nests them as the workflow's
``params.odometry`` keys (``icp: {max_corr_m: 1.0}``) and is what ``estimate_edges`` receives. Tests and benches
build it the same way (``OdometryParams(prepare={"voxel_m": 0.5})``) or a section directly.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from pipeline.declare import Params


class PrepareConfig(Params):
    """Per scan: range crop, voxel downsampling with ``knn`` neighbours for covariances / normals, and the road
    plane split (``ground_split``: points within ``ground_tolerance_m`` of the fitted plane are ground)."""

    voxel_m: float = Field(1.0, gt=0, description="voxel size of the downsampled clouds")
    knn: int = Field(20, ge=5, description="neighbours for covariances / normals")
    min_range_m: float = Field(2.0, ge=0, description="drop points closer (vehicle body)")
    max_range_m: float = Field(80.0, gt=0)
    ground_split: bool = Field(True, description="register the structure above the road plane only and take "
                               "height, roll and pitch from the two scans' road planes (removes the ground ring "
                               "pattern's pull towards zero motion)")
    ground_tolerance_m: float = Field(0.25, gt=0, description="points within this distance of the fitted road "
                                      "plane are ground")

    @model_validator(mode="after")
    def _ranges(self) -> "PrepareConfig":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self


class IcpConfig(Params):
    """Registration of the structure clouds (open3d GICP or point-to-plane ICP). ``guided_relative_tolerance``:
    the convergence criterion of a consecutive pair that starts from its wheel guide corrected by the previous pair's
    registration (``core.register_pairs``); every other registration stops at ``relative_tolerance``."""

    method: Literal["gicp", "point_to_plane"] = "gicp"
    max_corr_m: float = Field(1.0, gt=0, description="ICP correspondence distance")
    max_iterations: int = Field(15, ge=1)
    relative_tolerance: float = Field(1e-4, gt=0, description="ICP convergence (open3d's relative fitness and "
                                      "RMSE): span edges, pairs without a wheel guide, own-sweep second pass")
    guided_relative_tolerance: float = Field(3e-3, gt=0, description="same, for a consecutive pair started from its "
                                             "wheel guide corrected by the previous pair's registration: 1.5-1.8 GICP "
                                             "iterations instead of 2.6-3.1, ICP-only drift as at 1e-4 (chosen on "
                                             "gangnam seed 2 and demo seed 3, bench/bench_odometry_guess.py)")


class InformationConfig(Params):
    """An edge's 6x6 information: the point-to-plane Hessian at ``point_sigma_m`` per point, floored at
    ``min_sigma_m`` / ``min_sigma_rad``, plus a rotation std of ``rot_sigma_per_rad`` per radian turned."""

    point_sigma_m: float = Field(0.05, gt=0, description="per-point residual std for the information matrix "
                                 "(calibrated against truth, absorbs correlated residuals)")
    min_sigma_m: float = Field(0.003, gt=0, description="floor of an edge's translation std")
    min_sigma_rad: float = Field(0.0001, gt=0, description="floor of an edge's rotation std")
    rot_sigma_per_rad: float = Field(0.0001, ge=0, description="extra rotation std per radian of edge rotation "
                                     "(turns). Calibrated against truth with bench.bench_posegraph_root's edge table: "
                                     "with wheel-odometry deskew, gangnam's edges in turns are as good as on straights "
                                     "(0.0047 deg at 2-5 deg per edge) and 90-scan spans through a corner 0.008 deg. "
                                     "A vehicle whose deskew is poorer in turns (no wheel odometry, slip) needs more: "
                                     "re-check")


class GateConfig(Params):
    """Acceptance of an edge: fitness, and deviation from the reference increment (GNSS/INS, or the tighter
    ``_guide`` limits where a wheel-odometry guide exists)."""

    min_fitness: float = Field(0.3, ge=0, le=1, description="below: edge not accepted")
    max_deviation_m: float = Field(0.3, gt=0, description="ICP vs valid GNSS/INS increment (good to ~0.1 m); above: "
                                   "edge rejected")
    max_deviation_rad: float = Field(0.0175, gt=0, description="same, rotation angle (1 deg)")
    max_deviation_guide_m: float = Field(0.05, gt=0, description="ICP vs the wheel-odometry increment where the "
                                         "drive has one (10 Hz increments good to 1.5 cm on the simulator)")
    max_deviation_guide_rad: float = Field(0.0035, gt=0, description="same, rotation (0.2 deg)")


class KeyframeConfig(Params):
    """Pairs of scans further apart in time than ``min_dt_s`` (keyframes, metres apart; ``keyframes.py``): GICP in
    ``stages`` of (voxel m, correspondence m); started from the prior, the GNSS/INS, else a global registration
    (FPFH + RANSAC at ``global_voxel_m``); gated within hypot(the reference's limit, ``deviation_*_per_m`` x the
    pair's distance); information floored at ``sigma_*_per_m`` x that distance; rejected when its chord leaves the
    heading by more than ``max_sideslip_deg`` (a car follows its heading: ``keyframes.plausible_motion``).
    ``prior_gate_sigmas``: a prior's limit in its stated std (times sqrt 2: two poses)."""

    min_dt_s: float = Field(0.35, gt=0, description="a consecutive pair further apart in time is a keyframe pair "
                            "(keyframe drives, gaps): no constant-velocity start, coarse-to-fine GICP, spacing-aware "
                            "gate and information; a 5-20 Hz sweep never is one")
    stages: tuple[tuple[float, float], ...] = Field(((1.0, 2.0), (0.5, 0.5)), description="keyframe pairs' GICP "
                                                    "stages (voxel m, correspondence m), each from the last")
    deviation_m_per_m: float = Field(0.05, ge=0, description="keyframe gate: the reference's limit widened by this "
                                     "much per metre between the keyframes (hypot)")
    deviation_rad_per_m: float = Field(0.0035, ge=0, description="same, rotation (0.2 deg per metre)")
    sigma_m_per_m: float = Field(0.015, ge=0, description="keyframe edges' translation std floor per metre (tiny "
                                 "calibration seed 7 at 5.4 m: 0.08 m RMS from the truth's start)")
    sigma_rad_per_m: float = Field(0.0015, ge=0, description="same, rotation (0.43 deg RMS at 5.4 m)")
    global_voxel_m: float = Field(1.0, gt=0, description="voxel of the global registration (FPFH + RANSAC) that "
                                  "starts a keyframe pair without a prior or GNSS/INS")
    max_sideslip_deg: float = Field(15.0, gt=0, le=90, description="keyframe gate: the pair's chord within this of "
                                    "its heading plus half its turn, forward or reverse (a car follows its heading; "
                                    "90 = off, for a robot that moves sideways)")
    prior_gate_sigmas: float = Field(3.0, gt=0, description="gate against a prior trajectory's increment at this "
                                     "many times its stated std (x sqrt 2: two poses)")

    @property
    def max_sideslip_rad(self) -> float:
        return math.radians(self.max_sideslip_deg)
