"""Parameters of the odometry stage (defaults measured on simulated HDL-32E drives, see docs/posegraph.md)."""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from pipeline.declare import Params
from stages.odometry.config import (
    EdgeConfig,
    GateConfig,
    IcpConfig,
    InformationConfig,
    KeyframeConfig,
    PrepareConfig,
)


class OdometryParams(Params):
    method: Literal["gicp", "point_to_plane"] = "gicp"
    voxel_m: float = Field(1.0, gt=0, description="voxel size of the downsampled clouds")
    knn: int = Field(20, ge=5, description="neighbours for covariances / normals")
    max_corr_m: float = Field(1.0, gt=0, description="ICP correspondence distance")
    max_iterations: int = Field(15, ge=1)
    relative_tolerance: float = Field(1e-4, gt=0, description="ICP convergence (open3d's relative fitness and "
                                      "RMSE): span edges, pairs without a wheel guide, own-sweep second pass")
    guided_relative_tolerance: float = Field(3e-3, gt=0, description="same, for a consecutive pair started from "
                                             "its wheel guide corrected by the previous pair's registration: 1.5-1.8 "
                                             "GICP iterations instead of 2.6-3.1, ICP-only drift as at 1e-4 (chosen on "
                                             "gangnam seed 2 and demo seed 3, bench/bench_odometry_guess.py)")
    min_range_m: float = Field(2.0, ge=0, description="drop points closer (vehicle body)")
    max_range_m: float = Field(80.0, gt=0)
    deskew: Literal["odometry", "own_sweep", "none"] = Field(
        "odometry", description="motion compensation of each sweep: 'odometry' = wheel speed + yaw rate where the "
        "drive has them (own_sweep for the other scans), 'own_sweep' = a first ICP pass gives each scan the motion "
        "over its own sweep, then register again (2x cost), 'none'")
    ground_split: bool = Field(True, description="register the structure above the road plane only and take "
                               "height, roll and pitch from the two scans' road planes (removes the ground ring "
                               "pattern's pull towards zero motion)")
    ground_tolerance_m: float = Field(0.25, gt=0, description="points within this distance of the fitted road "
                                      "plane are ground")
    min_fitness: float = Field(0.3, ge=0, le=1, description="below: edge not accepted")
    max_deviation_m: float = Field(0.3, gt=0, description="ICP vs valid GNSS/INS increment (good to ~0.1 m); "
                                   "above: edge rejected")
    max_deviation_rad: float = Field(0.0175, gt=0, description="same, rotation angle (1 deg)")
    max_deviation_wheel_m: float = Field(0.05, gt=0, description="ICP vs the wheel-odometry increment where the "
                                         "drive has one (10 Hz increments good to 1.5 cm on the simulator)")
    max_deviation_wheel_rad: float = Field(0.0035, gt=0, description="same, rotation (0.2 deg)")
    point_sigma_m: float = Field(0.05, gt=0, description="per-point residual std for the information matrix "
                                 "(calibrated against truth, absorbs correlated residuals)")
    min_sigma_m: float = Field(0.003, gt=0, description="floor of an edge's translation std")
    min_sigma_rad: float = Field(0.0001, gt=0, description="floor of an edge's rotation std")
    rot_sigma_per_rad: float = Field(0.0001, ge=0, description="extra rotation std per radian of edge rotation "
                                     "(turns). Calibrated against truth with bench.bench_posegraph_root's edge "
                                     "table: with wheel-odometry deskew, gangnam's edges in turns are as good as "
                                     "on straights (0.0047 deg at 2-5 deg per edge) and 90-scan spans through "
                                     "a corner 0.008 deg; the former 0.03 claimed 14-300x that. A vehicle whose "
                                     "deskew is poorer in turns (no wheel odometry, slip) needs more: re-check")
    span_scans: list[int] = Field([10, 30, 90], description="also register every N-th scan of a chunk onto "
                                  "the scan N before it, for each N (span edges: one registration error over N "
                                  "scans instead of N chained ones; gangnam without survey: absolute 0.320 -> "
                                  "0.255 m, heading 0.096 -> 0.060 deg; ~6 % odometry time); [] = consecutive edges "
                                  "only")

    keyframe_min_dt_s: float = Field(0.35, gt=0, description="a consecutive pair further apart in time is a keyframe "
                                     "pair (keyframe drives, gaps): no constant-velocity start, coarse-to-fine GICP, "
                                     "spacing-aware gate and information; a 5-20 Hz sweep never is one")
    keyframe_stages: list[tuple[float, float]] = Field([(1.0, 2.0), (0.5, 0.5)], description="keyframe pairs' GICP "
                                                       "stages (voxel m, correspondence m), each from the last")
    keyframe_deviation_m_per_m: float = Field(0.05, ge=0, description="keyframe gate: the reference's limit widened "
                                              "by this much per metre between the keyframes (hypot)")
    keyframe_deviation_rad_per_m: float = Field(0.0035, ge=0, description="same, rotation (0.2 deg per metre)")
    keyframe_sigma_m_per_m: float = Field(0.015, ge=0, description="keyframe edges' translation std floor per metre "
                                          "(tiny calibration seed 7 at 5.4 m: 0.08 m RMS from the truth's start)")
    keyframe_sigma_rad_per_m: float = Field(0.0015, ge=0, description="same, rotation (0.43 deg RMS at 5.4 m)")
    keyframe_global_voxel_m: float = Field(1.0, gt=0, description="voxel of the global registration (FPFH + "
                                           "RANSAC) that starts a keyframe pair without a prior or GNSS/INS")
    keyframe_max_sideslip_deg: float = Field(15.0, gt=0, le=90, description="keyframe gate: the pair's chord within "
                                             "this of its heading plus half its turn, forward or reverse (a car "
                                             "follows its heading; 90 = off, for a robot that moves sideways)")
    prior_gate_sigmas: float = Field(3.0, gt=0, description="gate against a prior trajectory's increment at this "
                                     "many times its stated std (x sqrt 2: two poses)")

    def edge_config(self) -> EdgeConfig:
        """The algorithm's settings in sections (``estimate_edges`` never sees this params object)."""
        return EdgeConfig(
            prepare=PrepareConfig(voxel_m=self.voxel_m, knn=self.knn, min_range_m=self.min_range_m,
                                  max_range_m=self.max_range_m, ground_split=self.ground_split,
                                  ground_tolerance_m=self.ground_tolerance_m),
            icp=IcpConfig(method=self.method, max_corr_m=self.max_corr_m, max_iterations=self.max_iterations,
                          relative_tolerance=self.relative_tolerance,
                          guided_relative_tolerance=self.guided_relative_tolerance),
            information=InformationConfig(point_sigma_m=self.point_sigma_m, min_sigma_m=self.min_sigma_m,
                                          min_sigma_rad=self.min_sigma_rad, rot_sigma_per_rad=self.rot_sigma_per_rad),
            gate=GateConfig(min_fitness=self.min_fitness, max_deviation_m=self.max_deviation_m,
                            max_deviation_rad=self.max_deviation_rad, max_deviation_guide_m=self.max_deviation_wheel_m,
                            max_deviation_guide_rad=self.max_deviation_wheel_rad),
            deskew=self.deskew != "none", span_scans=tuple(self.span_scans),
            keyframe=KeyframeConfig(
                min_dt_s=self.keyframe_min_dt_s, stages=tuple((float(v), float(c)) for v, c in self.keyframe_stages),
                deviation_m_per_m=self.keyframe_deviation_m_per_m,
                deviation_rad_per_m=self.keyframe_deviation_rad_per_m, sigma_m_per_m=self.keyframe_sigma_m_per_m,
                sigma_rad_per_m=self.keyframe_sigma_rad_per_m, global_voxel_m=self.keyframe_global_voxel_m,
                prior_gate_sigmas=self.prior_gate_sigmas,
                max_sideslip_rad=float(np.radians(self.keyframe_max_sideslip_deg))))

    @model_validator(mode="after")
    def _ranges(self) -> "OdometryParams":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        if any(n < 2 for n in self.span_scans):
            raise ValueError(f"span_scans {self.span_scans}: every span must be >= 2 scans (1 is the consecutive "
                             "edge)")
        return self
