"""Typed parameters of the markings stage (defaults in code; unknown keys rejected)."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from stages.common.marking_raster.settings import MarkingRasterSettings


class MarkingParams(MarkingRasterSettings):
    source: Literal["auto", "survey", "drives"] = Field(
        "auto", description="point cloud behind the rasters: the survey cloud, the map drives' scans placed with "
        "poses_optimized (a mobile-mapping cloud), or auto = the survey when the workflow has one")
    surface_band_m: float = Field(0.15, ge=0, description="lowest consistent surface: a cell keeps only the points "
                                  "within this of the lowest height any scan saw there; higher points (traffic "
                                  "standing on the road in some scans, people, branches) are dropped before the "
                                  "statistics; 0 = every point counts")
    # Map from drive scans (when no survey cloud)
    min_range_m: float = Field(2.5, ge=0, description="closer lidar returns (the ego vehicle) are dropped")
    max_range_m: float = Field(25.0, gt=0, description="horizontal lidar range kept when accumulating scans")
    pose_buffer_m: float = Field(30.0, ge=0, description="tiles planned around the poses' path")
