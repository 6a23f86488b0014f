"""Parameters of the odometry stage (defaults measured on simulated HDL-32E drives, see docs/posegraph.md)."""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.declare import Params


class OdometryParams(Params):
    method: Literal["gicp", "point_to_plane"] = "gicp"
    voxel_m: float = Field(0.7, gt=0, description="voxel size of the downsampled clouds")
    knn: int = Field(20, ge=5, description="neighbours for covariances / normals")
    max_corr_m: float = Field(0.7, gt=0, description="ICP correspondence distance")
    max_iterations: int = Field(15, ge=1)
    relative_tolerance: float = Field(1e-4, gt=0)
    min_range_m: float = Field(2.0, ge=0, description="drop points closer (vehicle body)")
    max_range_m: float = Field(80.0, gt=0)
    deskew: bool = Field(False, description="register, deskew both scans with that motion, register again "
                         "(2x cost; no gain on consecutive scans at near-constant velocity, see docs)")
    min_fitness: float = Field(0.3, ge=0, le=1, description="below: edge marked not converged")
    max_deviation_m: float = Field(0.3, gt=0, description="ICP vs valid GNSS/INS increment (good to ~0.1 m); "
                                   "above: edge rejected")
    max_deviation_rad: float = Field(0.0175, gt=0, description="same, rotation angle (1 deg)")
    point_sigma_m: float = Field(0.15, gt=0, description="per-point residual std for the information matrix "
                                 "(calibrated against truth, absorbs correlated residuals)")
    min_sigma_m: float = Field(0.01, gt=0, description="floor of an edge's translation std")
    min_sigma_rad: float = Field(0.0003, gt=0, description="floor of an edge's rotation std")
    rot_sigma_per_rad: float = Field(0.03, ge=0, description="extra rotation std per radian of edge rotation "
                                     "(turns; calibrated against truth)")

    @model_validator(mode="after")
    def _ranges(self) -> "OdometryParams":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self
