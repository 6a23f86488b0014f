"""Schemas of the marking layer, map tiles and evaluation."""
import pyarrow as pa

from schemas.registry import field as f
from schemas.registry import register

register(
    "marking_raster", "Per tile raster metadata; rasters are PNG files beside it (see docs/map-format.md).",
    f("tile_i", pa.int32()), f("tile_j", pa.int32()),
    f("origin_east_m", pa.float64(), "m", "enu", doc="east of the raster's lower-left corner"),
    f("origin_north_m", pa.float64(), "m", "enu"),
    f("cell_m", pa.float64(), "m"), f("width_px", pa.int32()), f("height_px", pa.int32()),
    f("n_marking_px", pa.int64()), f("n_traversable_px", pa.int64()), f("n_points", pa.int64()),
    f("source", pa.string(), doc="survey | drives"),
)

register(
    "eval_epochs", "Per-epoch localization estimate, covariance and error vs the reference.",
    f("drive", pa.string()), f("method", pa.string()), f("epoch", pa.int64()), f("stamp_ns", pa.int64(), "ns"),
    f("x_m", pa.float64(), "m", "enu"), f("y_m", pa.float64(), "m", "enu"), f("yaw_rad", pa.float64(), "rad", "enu"),
    f("cov_xy_yaw", pa.list_(pa.float64(), 9)),
    f("err_x_m", pa.float64(), "m"), f("err_y_m", pa.float64(), "m"), f("err_yaw_rad", pa.float64(), "rad"),
    f("err_lateral_m", pa.float64(), "m"), f("err_longitudinal_m", pa.float64(), "m"),
    f("n_associated", pa.int32(), doc="EKF: map corners associated this epoch"),
    f("n_features", pa.int32(), doc="MCL: road-feature points used this epoch"),
    f("nees", pa.float64(), nullable=True, doc="normalised estimation error squared (3 dof)"),
)
