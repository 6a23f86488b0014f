"""Declaration of the corners stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.corners.params import CornerParams

STAGE = StageDecl(
    name="corners",
    summary="Per-scan vertical building corners from the upper LiDAR layers (Im et al. 2016 s.2).",
    code_version=code_version("3", "corners"),
    inputs={"scans": "scans_raw", "odometry": "odometry_raw", "drive_info": "drive_info"},
    optional_inputs=frozenset({"odometry", "drive_info"}),
    outputs={"corners": "corners_per_scan"},
    params=CornerParams,
    partition=Partitioning.PER_SCAN_CHUNK,
    partition_source="scans",
    compute="stages.corners.compute:compute",
    settings_keys=frozenset(),
)
