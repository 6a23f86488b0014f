"""Declaration of the corner map stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.cornermap.params import CornerMapParams

STAGE = StageDecl(
    name="cornermap",
    summary="Cluster per-scan corners across scans and drives into one covariance-filtered map record per corner",
    code_version=code_version("4", "cornermap"),
    inputs={"corners": "corners_per_scan", "poses": "poses_optimized", "drive_info": "drive_info"},
    outputs={"corner_map": "corner_map", "rejected": "corner_map_rejected"},
    params=CornerMapParams,
    partition=Partitioning.SINGLE,
    compute="stages.cornermap.compute:compute",
    settings_keys=frozenset({"map_drives"}),
)
