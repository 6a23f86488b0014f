"""Declaration of the odometry stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.odometry.params import OdometryParams

STAGE = StageDecl(
    name="odometry",
    summary="Deskewed structure-only GICP between consecutive scans, road planes for height/roll/pitch: vehicle-frame "
            "edges with fitness, RMSE, information; span edges over N scans.",
    code_version=code_version("10", "odometry"),
    inputs={"scans": "scans_raw", "poses_gnss": "poses_gnss", "drive_info": "drive_info", "odometry": "odometry_raw",
            "prior": "poses_prior"},
    optional_inputs=frozenset({"odometry", "prior"}),
    outputs={"edges": "odometry_edges", "span_edges": "odometry_span_edges"},
    params=OdometryParams,
    partition=Partitioning.PER_SCAN_CHUNK,
    partition_source="scans",
    compute="stages.odometry.compute:compute",
    settings_keys=frozenset(),
)
