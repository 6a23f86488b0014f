"""Typed params of the corner map stage (defaults in code, unknown keys rejected)."""
from __future__ import annotations

from pydantic import Field, model_validator

from pipeline.declare import Params


class CornerMapParams(Params):
    # Clustering (clustering.py): a radius graph on east/north, capped at k neighbours, gated by direction angles.
    link_radius_m: float = Field(0.35, gt=0.0, description="two observations closer than this may be linked")
    frame_check_match_m: float = Field(1.0, gt=0.0, description="corner layer vs poses check: an observation "
                                       "placed with its drive's optimized pose matches a map corner within this")
    frame_check_warn_m: float = Field(0.05, gt=0.0, description="warn when a drive's median offset exceeds this")
    angle_tol_deg: float = Field(12.0, gt=0.0, lt=90.0,
                                 description="both wall directions must agree within this to link")
    max_neighbors: int = Field(24, ge=2, description="k of the k-nearest-neighbour graph (bounds the work)")
    split_spread_m: float = Field(0.25, gt=0.0,
                                  description="a cluster whose principal std exceeds this is split by 2-means")
    # Duplicates (merge.py): clusters of one physical corner that the link radius split.
    merge_radius_m: float = Field(1.0, ge=0.0, description="clusters closer than this whose walls agree within "
                                  "angle_tol_deg are one corner: merged when the merged cluster passes the filter, "
                                  "else only the strongest is kept; 0 = off")
    # Spatial partitioning: square cells with a halo; a cluster belongs to the cell holding its centroid.
    cell_size_m: float = Field(200.0, gt=0.0)
    halo_m: float = Field(10.0, gt=0.0, description="must exceed twice the widest cluster plus link_radius_m")
    workers: int = Field(2, ge=1, description="threads clustering cells in parallel")
    # Filtering (filtering.py), after Im et al.: drop clusters with a large covariance or a small count.
    # 4, not 8: real HDL-64E facades give each corner fewer observations (docs/corners.md, "Real facades and the
    # gates"); chosen on kitti_city / tiny_consumer calibration seeds thinned to the real extraction rate
    min_obs: int = Field(4, ge=1, description="fewer observations than this -> rejected")
    min_drives: int = Field(1, ge=1)
    # 0.25 m, not 0.15: with a GNSS-level pose graph the scatter is dominated by the poses (tiny drive_0: a corner
    # seen from 8-44 m scatters 0.21 m through the optimized poses, 0.03 m through the true ones), see
    # CHANGELOG.md (evaluation measurements, the tiny diagnosis).
    max_spread_m: float = Field(0.25, gt=0.0,
                                description="largest std of the observations' scatter about the mean")
    max_cov_trace_m2: float = Field(0.01, gt=0.0, description="trace of the extraction part of the map covariance, "
                                    "averaged over every observation")
    extraction_error_per_drive: bool = Field(True, description="the stored covariance's empirical extraction part "
                                             "is the observations' scatter over the number of drives (one pass's "
                                             "views share their extraction error); false: over the number of "
                                             "observations")
    pass_autocorrelation: bool = Field(True, description="with extraction_error_per_drive: a pass counts the "
                                       "effective number of independent samples among its views, n (1 - rho) / "
                                       "(1 + rho), rho the lag-1 correlation of the views' deviations measured on "
                                       "the map's own passes (aggregate.lag_one_correlation); false: one per pass")
    pass_shared_fraction: float = Field(0.0, ge=0.0, le=10.0, description="with pass_autocorrelation: the "
                                        "variance of a part of a pass's extraction error its views share (the "
                                        "same walls; it does not decorrelate with lag and does not scatter) over "
                                        "the variance of the views' own part (aggregate.pass_mean_factor); 0: none")
    pose_shared_per_pass: bool = Field(True, description="the pose part of a corner's covariance: a pass's poses "
                                       "share their error, propagated through the weighted mean's Jacobian "
                                       "(aggregate.shared_pose_part); false: each view's propagated pose "
                                       "covariance averaged")
    max_angle_spread_deg: float = Field(6.0, gt=0.0, description="circular std of either wall direction")

    @model_validator(mode="after")
    def _check_halo(self) -> "CornerMapParams":
        if self.halo_m < 4.0 * self.link_radius_m:
            raise ValueError(f"halo_m {self.halo_m} m must be >= 4 x link_radius_m ({4 * self.link_radius_m} m) "
                             "so that no cluster is cut at a cell border")
        if self.halo_m >= self.cell_size_m:
            raise ValueError(f"halo_m {self.halo_m} m must be < cell_size_m {self.cell_size_m} m")
        return self
