"""Typed parameters of corner extraction, in one section per step of the chain (Im et al. 2016 s.2): ``layers``,
``lines``, ``candidates``, ``clusters``, ``checks``. Each section is what its step's functions receive; every field
states its unit; `cornermap corners params` prints them."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.declare import Params


class LayerParams(Params):
    """1. Layer selection: which rings are used, and the range window of their points."""

    layer_selection: Literal["elevation", "top_n"] = Field(
        "elevation",
        description="'elevation': rings whose estimated elevation (robust mean of atan2(z, hypot(x, y))) "
        ">= min_elevation_deg, at most n_upper_layers of the highest; 'top_n': the n_upper_layers highest ring "
        "indices (trusting ring 0 = lowest beam).",
    )
    n_upper_layers: int = Field(
        8,
        ge=1,
        le=128,
        description="Number of upper layers used [rings]; the paper uses the eight upper HDL-32E beams.",
    )
    min_elevation_deg: float = Field(
        -1.0, ge=-90.0, le=90.0, description="Lowest ring elevation kept in 'elevation' mode [deg], sensor frame."
    )
    min_range_m: float = Field(2.0, ge=0.0, description="Points nearer than this are dropped (own vehicle) [m].")
    max_range_m: float = Field(80.0, gt=0.0, description="Points farther than this are dropped [m].")
    deskew: bool = Field(
        True,
        description="Motion-compensate each scan to its start time by integrating the "
        "wheel speed and yaw rate of odometry_raw over the revolution, when that input exists; "
        "otherwise each corner carries the mean time of its points [bool].",
    )

    @model_validator(mode="after")
    def _check_range_window(self) -> "LayerParams":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be < max_range_m ({self.max_range_m})")
        return self


class LineParams(Params):
    """2-3. Line extraction (breakpoints, IEPF split and merge, TLS refit) and outlier removal."""

    break_incidence_deg: float = Field(
        10.0,
        gt=0.0,
        lt=90.0,
        description="Adaptive breakpoint (Borges & "
        "Aldon 2004): a surface seen at a grazing angle below this breaks the "
        "ring between consecutive points [deg].",
    )
    range_sigma_m: float = Field(
        0.03, gt=0.0, description="Range noise of the sensor, 1 sigma [m]; widens the breakpoint threshold by 3 sigma."
    )
    max_azimuth_gap_deg: float = Field(
        1.0,
        gt=0.0,
        description="A gap in azimuth between consecutive returns "
        "larger than this (missing returns: glass, sky) breaks the ring [deg].",
    )
    split_distance_m: float = Field(
        0.10,
        gt=0.0,
        description="IEPF: a segment is split at its farthest point "
        "when that point is farther than this from the end-point chord [m].",
    )
    merge_max_angle_deg: float = Field(
        2.0,
        ge=0.0,
        description="Merge step: adjacent split segments whose "
        "directions differ by less than this and whose centroids lie within "
        "split_distance_m of each other's line are merged [deg].",
    )
    end_trim_points: int = Field(
        1,
        ge=0,
        le=5,
        description="Points left out at each end of a segment in the "
        "total-least-squares refit (mixed pixels at corners and edges) [points].",
    )
    max_residual_var_m2: float = Field(
        0.0016,
        gt=0.0,
        description="Paper Figure 5: lines whose mean squared "
        "perpendicular residual exceeds this are outliers (tree crowns) [m^2]; "
        "0.0016 m^2 = (0.04 m)^2.",
    )
    min_points: int = Field(6, ge=3, description="Minimum points of a line [points].")
    min_length_m: float = Field(0.8, ge=0.0, description="Minimum length of a line along its direction [m].")


class CandidateParams(Params):
    """4. Corner candidates: two neighbouring lines of one layer that meet."""

    max_corner_gap_m: float = Field(
        0.6,
        gt=0.0,
        description="The intersection of two neighbouring lines must "
        "lie within this of the facing end point of each line [m].",
    )
    min_interior_angle_deg: float = Field(
        50.0, gt=0.0, lt=180.0, description="Smallest angle between the two walls of a candidate [deg]."
    )
    max_interior_angle_deg: float = Field(
        155.0,
        gt=0.0,
        lt=180.0,
        description="Largest angle between the two walls of a candidate [deg]; obtuse and chamfered corners are kept.",
    )

    @model_validator(mode="after")
    def _check_angle_band(self) -> "CandidateParams":
        if self.min_interior_angle_deg >= self.max_interior_angle_deg:
            raise ValueError(
                f"min_interior_angle_deg ({self.min_interior_angle_deg}) must be < "
                f"max_interior_angle_deg ({self.max_interior_angle_deg})"
            )
        return self


class ClusterParams(Params):
    """5. Corner determination: candidates of several layers clustered into one corner, its covariance."""

    cluster_radius_m: float = Field(
        0.3,
        gt=0.0,
        description="Candidates of different layers closer than this "
        "in the horizontal plane belong to the same corner [m].",
    )
    cluster_max_angle_deg: float = Field(
        15.0, gt=0.0, description="... and whose wall directions differ by less than this [deg]."
    )
    min_layers: int = Field(
        3,
        ge=2,
        description="Redundancy check: a corner needs candidates from at least this many distinct layers [layers].",
    )
    angular_sigma_mrad: float = Field(
        1.0,
        ge=0.0,
        description="Angular error common to all layers of a scan "
        "(deskew residual, azimuth jitter), added to each corner's covariance as "
        "an isotropic (range x sigma)^2 term; 1 mrad = 0.05 m at 50 m [mrad].",
    )
    min_sigma_m: float = Field(
        0.01,
        gt=0.0,
        description="Floor of each line's residual sigma and of every "
        "corner covariance eigenvalue, 1 sigma (range and azimuth quantisation) [m].",
    )


class CheckParams(Params):
    """6. The checks a determined corner must pass: small structures, vertex support, near corners, short objects."""

    min_wall_length_m: float = Field(
        0.0,
        ge=0.0,
        description="Small-structure check: the shorter wall of a corner, "
        "as the longest line any of its layers saw on that side, must be at least "
        "this long; off by default: real facades seen at a grazing angle show side "
        "walls of 1-1.5 m per ring (KITTI, nuScenes samples) [m].",
    )
    min_long_wall_length_m: float = Field(
        2.0,
        ge=0.0,
        description="... and the longer wall at least this long: "
        "cars (the rear of a lead vehicle: walls 1.0-1.4 m), kiosks and shelters "
        "with walls under 2 m, and the chords of a rounded corner give no "
        "corner [m].",
    )
    obtuse_angle_deg: float = Field(
        120.0, gt=0.0, lt=180.0, description="Corners with a wider interior angle are obtuse for the next check [deg]."
    )
    min_obtuse_wall_length_m: float = Field(
        2.0,
        ge=0.0,
        description="An obtuse corner's shorter wall must be at "
        "least this long: a rounded corner (radius 1-5 m) is cut into chords "
        "under 2 m that meet each other and the straight walls at obtuse "
        "angles, so it gives no corner; a chamfer facet shorter than this "
        "counts as rounded, a longer one gives two obtuse corners [m].",
    )
    max_vertex_gap_spacings: float = Field(
        1.0,
        ge=0.0,
        description="Vertex support: at least one layer must see "
        "one of the two lines reach the corner, its facing end point within this "
        "many of that line's point spacings of the lines' intersection. A "
        "corner extrapolated into empty space (the chord of a rounded corner "
        "meeting a straight wall past the part of the arc the line split left "
        "out) gives none; 0 disables [spacings].",
    )
    min_corner_range_m: float = Field(
        8.0,
        ge=0.0,
        description="Corners nearer than this are dropped: there even "
        "the top HDL-32E layer passes only 1.5 m above the sensor, so a building "
        "cannot be told from a bus or truck alongside [m].",
    )
    max_passover_height_m: float = Field(
        2.5,
        ge=0.0,
        description="Short-object check: a corner is dropped when "
        "a higher layer, passing at most this high above the sensor at the "
        "corner's range, returns nothing at or before the corner (it flew over "
        "a truck or bus); 0 disables [m].",
    )


class CornerParams(Params):
    """Defaults are tuned for Velodyne HDL-32E / HDL-64E class sensors (about 0.1-0.2 deg azimuth step)."""

    renamed = {
        key: f"{section}.{key}"
        for section, keys in {
            "layers": [
                "layer_selection",
                "n_upper_layers",
                "min_elevation_deg",
                "min_range_m",
                "max_range_m",
                "deskew",
            ],
            "lines": [
                "break_incidence_deg",
                "range_sigma_m",
                "max_azimuth_gap_deg",
                "split_distance_m",
                "merge_max_angle_deg",
                "end_trim_points",
                "max_residual_var_m2",
                "min_points",
                "min_length_m",
            ],
            "candidates": ["max_corner_gap_m", "min_interior_angle_deg", "max_interior_angle_deg"],
            "clusters": [
                "cluster_radius_m",
                "cluster_max_angle_deg",
                "min_layers",
                "angular_sigma_mrad",
                "min_sigma_m",
            ],
            "checks": [
                "min_wall_length_m",
                "min_long_wall_length_m",
                "obtuse_angle_deg",
                "min_obtuse_wall_length_m",
                "max_vertex_gap_spacings",
                "min_corner_range_m",
                "max_passover_height_m",
            ],
        }.items()
        for key in keys
    }

    layers: LayerParams = LayerParams()
    lines: LineParams = LineParams()
    candidates: CandidateParams = CandidateParams()
    clusters: ClusterParams = ClusterParams()
    checks: CheckParams = CheckParams()

    @model_validator(mode="after")
    def _check_layers(self) -> "CornerParams":
        if self.clusters.min_layers > self.layers.n_upper_layers:
            raise ValueError(
                f"clusters.min_layers ({self.clusters.min_layers}) cannot exceed layers.n_upper_layers "
                f"({self.layers.n_upper_layers})"
            )
        return self
