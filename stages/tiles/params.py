"""Parameters of the tiles stage: grid, retention and the quality gates run before publishing."""
from __future__ import annotations

from pydantic import Field

from pipeline.declare import Params
from stages.common.tiling import DEFAULT_TILE_SIZE_M


class TilesParams(Params):
    tile_size_m: float | None = Field(None, gt=0, description="tile edge in metres; None = the workflow's "
                                                               f"tile_size_m setting ({DEFAULT_TILE_SIZE_M:g} m "
                                                               "when unset), so tiles line up with the marking "
                                                               "rasters")
    keep_last: int = Field(5, ge=1, description="versions kept; older ones are deleted, never the LATEST one")
    gates_enabled: bool = Field(True, description="run the quality gates below before publishing")
    min_corners_per_km: float = Field(10.0, ge=0, description="corners per km of optimized driven path, each "
                                                              "street counted once however many drives took it "
                                                              "(distinct_path_radius_m; Im et al. 2016 report "
                                                              "~135/km in Gangnam)")
    distinct_path_radius_m: float = Field(10.0, gt=0, description="the corner density's driven km: a stretch "
                                          "of a drive within this of an earlier drive's path is a street already "
                                          "counted (a road's lanes both ways lie within it)")
    max_empty_path_tile_share: float = Field(0.5, ge=0, le=1, description="largest share of tiles along the "
                                                                          "driven path holding no corner")
    check_schema: bool = Field(True, description="gate: corner table matches corner_map, finite values, "
                                                 "PSD covariances, unique ids; raster rows on the tile grid")
    path_step_m: float = Field(5.0, gt=0, description="spacing used to densify the driven path when "
                                                      "finding the tiles it crosses")
    id_max_dist_m: float = Field(1.0, gt=0, description="corner identity: a corner keeps the previous version's "
                                                        "id only within this distance (mapformat/corner_ids.py)")
    id_max_angle_deg: float = Field(15.0, gt=0, le=90, description="corner identity: both wall directions "
                                                                  "within this angle of the previous corner's")
    changelog_move_threshold_m: float = Field(0.2, ge=0, description="recorded in the changelog for readers of its "
                                              "format 1 (moved by distance); format 2 lists a corner as moved by "
                                              "changelog_significance")
    changelog_significance: float = Field(0.001, gt=0, lt=1, description="changelog: a kept corner is moved when "
                                          "the chi-square test (2 dof) on its displacement with both covariances "
                                          "rejects 'unchanged' at this level; a marking cell is changed by its "
                                          "binomial test at this level (mapformat/change_tests.py)")
    changelog_min_obs: int = Field(8, ge=1, description="observations the corner map needs to keep a corner (its "
                                   "cornermap stage's min_obs): an unmatched corner is removed / added only when "
                                   "the other version's drives had it in view from at least this many scans")
    localizability: bool = Field(True, description="publish the localizability layer: per cell of the driven roads "
                                 "the predicted position uncertainty of the corner EKF and of the marking MCL "
                                 "(tiles/{i}_{j}/localizability.parquet; stages/common/localizability.py)")
    localizability_cell_m: float = Field(10.0, gt=0, description="the layer's cell edge (divides the tile edge)")
    localizability_detection_rate: float = Field(0.58, gt=0, le=1, description="share of the corners in view an "
                                                 "EKF look associates: the EKF's associations over the corners "
                                                 "predicted in view, tiny calibration seeds 221 / 222 / 223: 0.665 / "
                                                 "0.584 / 0.478, mean 0.58 (docs/map-format.md)")
    localizability_weak_sigma_m: float = Field(0.10, gt=0, description="a cell predicted above this sigma_2d is "
                                               "'weak' (the EKF's RMS target)")
    localizability_fail_sigma_m: float = Field(0.40, gt=0, description="... above this 'fail' (the EKF's max "
                                               "target)")
    # Tile-local re-derivation (stages/tiles/tilelocal.py; docs/maintenance.md, "Tiles of an incremental rebuild")
    tile_local: bool = Field(True, description="a tile the new version does not touch keeps its parent's files byte "
                             "for byte (same sha256); false: every tile is written from this version's derivation")
    tile_local_corner_tol_m: float = Field(0.005, ge=0, description="a corner of an untouched tile is kept as "
                                           "published when the re-derivation places it within this (and it has the "
                                           "same observations); farther: its tile is re-derived")
    tile_local_cov_tol_rel: float = Field(0.1, ge=0, description="... and its covariance changed by at most this "
                                          "share (Frobenius norm)")
    tile_local_pose_tol_m: float = Field(0.005, ge=0, description="a map pose moved by more than this (|dt| + "
                                         "tile_local_reach_m x rotation angle) is a changed pose: the tile holding "
                                         "it is re-derived (the localizability layer samples the drives' paths)")
    tile_local_reach_m: float = Field(25.0, gt=0, description="lever arm of a pose's rotation in its move: the "
                                      "markings stage's max_range_m (how far a pose paints the rasters)")
