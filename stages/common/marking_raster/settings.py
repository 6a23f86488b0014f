"""Road-marking raster settings (Kim et al. s.2.1), shared by every stage that rasterizes markings.

A stage embeds ``MarkingRasterSettings`` in its own params (the markings stage inherits its fields flat; the pose
graph's survey anchors hold a ``survey_marking_raster`` section), so each stage's fingerprint sees its own values.
"""
from __future__ import annotations

from pydantic import Field, model_validator

from pipeline.declare import Params


class MarkingRasterSettings(Params):
    # Grid
    cell_m: float = Field(0.1, gt=0, description="raster cell size, metres")
    min_points_per_cell: int = Field(1, ge=1, description="cells with fewer points are empty")
    # Traversable cells (elevation grid)
    max_step_m: float = Field(0.05, gt=0, description="max height difference of a cell's minimum to any of "
                                                       "its 8 neighbours' minima")
    max_spread_m: float = Field(0.15, gt=0, description="max min-to-max height spread inside one cell")
    ground_window_m: float = Field(4.0, gt=0, description="morphological opening window of the ground "
                                                          "surface; wider than any car or bus")
    max_above_ground_m: float = Field(0.3, gt=0, description="cells higher than this above the opened "
                                                             "ground (car roofs) are not traversable")
    # Markings (adaptive threshold on the intensity image)
    threshold_block_m: float = Field(2.5, gt=0, description="adaptive threshold neighbourhood, metres "
                                                            "(converted to an odd pixel count)")
    threshold_offset_sigma: float = Field(3.0, ge=0, description="paint must exceed the local mean by this "
                                                                 "many robust sigmas of the high-passed "
                                                                 "road intensity")
    threshold_min_offset_levels: float = Field(6.0, ge=0, description="floor of that offset, in levels of "
                                                                      "the 8-bit normalised intensity")
    intensity_low_pct: float = Field(1.0, ge=0, lt=100, description="percentile mapped to 8-bit level 0")
    intensity_high_pct: float = Field(99.5, gt=0, le=100, description="percentile mapped to level 255")
    open_m: float = Field(0.0, ge=0, description="morphological opening of the mask (0 = off)")
    close_m: float = Field(0.0, ge=0, description="morphological closing of the mask (0 = off)")
    min_region_m2: float = Field(4.0, ge=0, description="traversable regions (split by curbs) at least this "
                                                        "large are thresholded on their own")
    min_marking_area_m2: float = Field(0.05, ge=0, description="drop marking blobs smaller than this")

    def rasterize_kwargs(self) -> dict:
        """Keyword arguments of ``rasterize.rasterize_grid`` from these params (the stage and the pose graph's
        survey marking anchors build their marking masks with the same call)."""
        return dict(min_points=self.min_points_per_cell, max_step_m=self.max_step_m, max_spread_m=self.max_spread_m,
                    ground_window_m=self.ground_window_m, max_above_ground_m=self.max_above_ground_m,
                    threshold_block_m=self.threshold_block_m, threshold_offset_sigma=self.threshold_offset_sigma,
                    threshold_min_offset_levels=self.threshold_min_offset_levels,
                    intensity_low_pct=self.intensity_low_pct, intensity_high_pct=self.intensity_high_pct,
                    open_m=self.open_m, close_m=self.close_m, min_marking_area_m2=self.min_marking_area_m2,
                    min_region_m2=self.min_region_m2)

    @model_validator(mode="after")
    def _check(self) -> "MarkingRasterSettings":
        problems = []
        if self.threshold_block_m < 3 * self.cell_m:
            problems.append(f"threshold_block_m {self.threshold_block_m} m must be >= 3 cells "
                            f"({3 * self.cell_m} m)")
        if self.intensity_high_pct <= self.intensity_low_pct:
            problems.append(f"intensity_high_pct {self.intensity_high_pct} must exceed intensity_low_pct "
                            f"{self.intensity_low_pct}")
        if self.ground_window_m < 3 * self.cell_m:
            problems.append(f"ground_window_m {self.ground_window_m} m must be >= 3 cells")
        if problems:
            raise ValueError("; ".join(problems))
        return self
