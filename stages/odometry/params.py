"""Parameters of the odometry stage: the algorithm's config sections (config.py) nested as the workflow's
``params.odometry`` keys; ``estimate_edges`` receives this object. Defaults measured on simulated HDL-32E drives, see
docs/posegraph.md."""
from __future__ import annotations

from typing import ClassVar, Literal, Mapping

from pydantic import Field, model_validator

from pipeline.declare import Params
from stages.odometry.config import GateConfig, IcpConfig, InformationConfig, KeyframeConfig, PrepareConfig


class OdometryParams(Params):
    """All of ``estimate_edges``' settings: the sections, the motion compensation and the span edges."""

    prepare: PrepareConfig = Field(default_factory=PrepareConfig)
    icp: IcpConfig = Field(default_factory=IcpConfig)
    information: InformationConfig = Field(default_factory=InformationConfig)
    gate: GateConfig = Field(default_factory=GateConfig)
    keyframe: KeyframeConfig = Field(default_factory=KeyframeConfig)
    deskew: Literal["odometry", "own_sweep", "none"] = Field(
        "odometry", description="motion compensation of each sweep: 'odometry' = wheel speed + yaw rate where the "
        "drive has them (own_sweep for the other scans), 'own_sweep' = a first ICP pass gives each scan the motion "
        "over its own sweep, then register again (2x cost), 'none'")
    span_scans: tuple[int, ...] = Field((10, 30, 90), description="also register every N-th scan of a chunk onto "
                                        "the scan N before it, for each N (span edges: one registration error over N "
                                        "scans instead of N chained ones; gangnam without survey: absolute 0.320 -> "
                                        "0.255 m, heading 0.096 -> 0.060 deg; ~6 % odometry time); [] = consecutive "
                                        "edges only")

    # the flat keys of before the sections -> their place now (refused with it)
    renamed: ClassVar[Mapping[str, str]] = {
        "method": "icp.method",
        "voxel_m": "prepare.voxel_m",
        "knn": "prepare.knn",
        "min_range_m": "prepare.min_range_m",
        "max_range_m": "prepare.max_range_m",
        "ground_split": "prepare.ground_split",
        "ground_tolerance_m": "prepare.ground_tolerance_m",
        "max_corr_m": "icp.max_corr_m",
        "max_iterations": "icp.max_iterations",
        "relative_tolerance": "icp.relative_tolerance",
        "guided_relative_tolerance": "icp.guided_relative_tolerance",
        "point_sigma_m": "information.point_sigma_m",
        "min_sigma_m": "information.min_sigma_m",
        "min_sigma_rad": "information.min_sigma_rad",
        "rot_sigma_per_rad": "information.rot_sigma_per_rad",
        "min_fitness": "gate.min_fitness",
        "max_deviation_m": "gate.max_deviation_m",
        "max_deviation_rad": "gate.max_deviation_rad",
        "max_deviation_wheel_m": "gate.max_deviation_guide_m",
        "max_deviation_wheel_rad": "gate.max_deviation_guide_rad",
        "keyframe_min_dt_s": "keyframe.min_dt_s",
        "keyframe_stages": "keyframe.stages",
        "keyframe_deviation_m_per_m": "keyframe.deviation_m_per_m",
        "keyframe_deviation_rad_per_m": "keyframe.deviation_rad_per_m",
        "keyframe_sigma_m_per_m": "keyframe.sigma_m_per_m",
        "keyframe_sigma_rad_per_m": "keyframe.sigma_rad_per_m",
        "keyframe_global_voxel_m": "keyframe.global_voxel_m",
        "keyframe_max_sideslip_deg": "keyframe.max_sideslip_deg",
        "prior_gate_sigmas": "keyframe.prior_gate_sigmas",
    }

    @property
    def own_sweep_deskew(self) -> bool:
        """Whether a scan not deskewed before (no wheel odometry) gets the motion over its own sweep."""
        return self.deskew != "none"

    def registration_kwargs(self, guided: bool = False) -> dict:
        """The keywords of ``stages.common.registration.register_clouds`` (``guided``: of a consecutive pair started
        from its corrected wheel guide)."""
        i, icp = self.information, self.icp
        tol = icp.guided_relative_tolerance if guided else icp.relative_tolerance
        return dict(method=icp.method, max_corr_m=icp.max_corr_m, max_iterations=icp.max_iterations,
                    relative_tolerance=tol, point_sigma_m=i.point_sigma_m, min_sigma_m=i.min_sigma_m,
                    min_sigma_rad=i.min_sigma_rad)

    @model_validator(mode="after")
    def _spans(self) -> "OdometryParams":
        if any(n < 2 for n in self.span_scans):
            raise ValueError(f"span_scans {list(self.span_scans)}: every span must be >= 2 scans (1 is the "
                             "consecutive edge)")
        return self
