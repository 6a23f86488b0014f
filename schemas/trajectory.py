"""Schemas of the pose graph stage."""
import pyarrow as pa

from schemas.registry import field as f
from schemas.registry import register

DRIVE = f("drive", pa.string())
POSE = [
    f("x_m", pa.float64(), "m", "enu"), f("y_m", pa.float64(), "m", "enu"), f("z_m", pa.float64(), "m", "enu"),
    f("qx", pa.float64()), f("qy", pa.float64()), f("qz", pa.float64()), f("qw", pa.float64()),
]

def _edge_fields(frame: str) -> list:
    """Increment of the vehicle frame expressed in ``frame`` (the pair's earlier scan), then its quality."""
    return [
        f("stamp_ns", pa.int64(), "ns"),
        f("dx_m", pa.float64(), "m", frame), f("dy_m", pa.float64(), "m", frame), f("dz_m", pa.float64(), "m", frame),
        f("qx", pa.float64()), f("qy", pa.float64()), f("qz", pa.float64()), f("qw", pa.float64()),
        f("fitness", pa.float64(), doc="share of source points with a correspondence"),
        f("inlier_rmse_m", pa.float64(), "m"),
        f("information", pa.list_(pa.float64(), 36), doc="6x6 row-major, gtsam order (rx ry rz tx ty tz)"),
        f("accepted", pa.bool_(), doc="the odometry gate accepted the edge (registered, fitness, deviation)"),
    ]


register(
    "odometry_edges", "ICP between consecutive scans: T_prev_curr of the vehicle frame, with quality.",
    DRIVE, f("chunk", pa.int32()),
    f("scan_id", pa.int64(), doc="the later scan of the pair; the earlier is scan_id - 1"),
    *_edge_fields("vehicle_prev"),
)

register(
    "odometry_span_edges", "ICP between scans N apart in a chunk (N in the odometry's span_scans), started from and "
    "gated against the chain of consecutive edges: T_from_to of the vehicle frame, with quality.",
    DRIVE, f("chunk", pa.int32()),
    f("scan_id_from", pa.int64(), doc="the earlier scan of the pair"),
    f("scan_id", pa.int64(), doc="the later scan of the pair"),
    *_edge_fields("vehicle_from"),
)

register(
    "poses_odometry", "Dead-reckoned vehicle poses from chained ICP edges (T_odom_vehicle).",
    DRIVE, f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"), *POSE,
)

register(
    "poses_optimized", "Pose-graph optimized vehicle poses T_map_vehicle with marginal covariance.",
    DRIVE, f("scan_id", pa.int64()), f("stamp_ns", pa.int64(), "ns"), *POSE,
    f("cov_xy_yaw", pa.list_(pa.float64(), 9), doc="3x3 row-major marginal covariance of (east m, north m, yaw rad) "
      "relative to the map frame; the frame's own error against ENU is the dataset's map_frame metadata "
      "(docs/posegraph.md)"),
)

register(
    "loop_closures", "Every loop-closure candidate with its scores and decision.",
    f("drive_a", pa.string()), f("scan_a", pa.int64()), f("drive_b", pa.string()), f("scan_b", pa.int64()),
    f("prior_distance_m", pa.float64(), "m"), f("fitness", pa.float64()), f("inlier_rmse_m", pa.float64(), "m"),
    f("dx_m", pa.float64(), "m"), f("dy_m", pa.float64(), "m"), f("dyaw_rad", pa.float64(), "rad"),
    f("accepted", pa.bool_()), f("reason", pa.string()),
)
