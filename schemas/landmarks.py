"""Schemas of corner extraction and the corner map."""
import pyarrow as pa

from schemas.registry import field as f
from schemas.registry import register

register(
    "corners_per_scan", "Vertical corners extracted from one scan, in the lidar frame (Im et al. 2016 s.2).",
    f("drive", pa.string()), f("chunk", pa.int32()),
    f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"), f("corner_idx", pa.int32()),
    f("x_m", pa.float64(), "m", "lidar"), f("y_m", pa.float64(), "m", "lidar"),
    f("theta1_rad", pa.float64(), "rad", "lidar", doc="direction from the corner along wall 1; "
      "canonical order: wrap(theta2 - theta1) in (0, pi] (docs/cornermap.md)"),
    f("theta2_rad", pa.float64(), "rad", "lidar", doc="direction from the corner along wall 2"),
    f("cov_xx_m2", pa.float64(), "m^2"), f("cov_xy_m2", pa.float64(), "m^2"), f("cov_yy_m2", pa.float64(), "m^2"),
    f("n_layers", pa.int16()), f("range_m", pa.float64(), "m"),
    f("interior_angle_rad", pa.float64(), "rad"), f("convex", pa.bool_()),
    f("time_offset_s", pa.float64(), "s", doc="time after the scan start at which the corner position holds; "
      "0 when deskewed"),
)

register(
    "corner_map",
    "One record per physical corner in the map's ENU frame (Im et al. 2016 Table 1).",
    f("corner_id", pa.int64()),
    f("east_m", pa.float64(), "m", "enu"),
    f("north_m", pa.float64(), "m", "enu"),
    f("theta1_rad", pa.float64(), "rad", "enu", doc="canonical order: wrap(theta2 - theta1) in (0, pi]"),
    f("theta2_rad", pa.float64(), "rad", "enu"),
    f("cov_ee_m2", pa.float64(), "m^2", doc="uncertainty of the map point (docs/cornermap.md)"),
    f("cov_en_m2", pa.float64(), "m^2"),
    f("cov_nn_m2", pa.float64(), "m^2"),
    f("n_obs", pa.int64()),
    f("n_drives", pa.int32()),
    f("drives", pa.string(), doc="comma-separated"),
    f("first_seen_ns", pa.int64(), "ns"),
    f("last_seen_ns", pa.int64(), "ns"),
    f("interior_angle_rad", pa.float64(), "rad"),
    f("convex", pa.bool_()),
)

register(
    "corner_map_rejected", "Clusters removed by the covariance/count filter, with the reason.",
    f("east_m", pa.float64(), "m", "enu"), f("north_m", pa.float64(), "m", "enu"),
    f("n_obs", pa.int64()), f("cov_trace_m2", pa.float64(), "m^2"), f("reason", pa.string()),
)
