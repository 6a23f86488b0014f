"""Declaration of the posegraph stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.posegraph.params import PosegraphParams

STAGE = StageDecl(
    name="posegraph",
    summary="GTSAM pose graph: ICP odometry and span edges, verified robust loop closures, robust GNSS priors, "
            "survey anchors; without GNSS, the prior trajectory and the start pose.",
    code_version=code_version("21", "posegraph"),
    inputs={"edges": "odometry_edges", "span_edges": "odometry_span_edges", "poses_gnss": "poses_gnss",
            "scans": "scans_raw", "drive_info": "drive_info", "survey": "survey_enu", "odometry": "odometry_raw",
            "prior": "poses_prior"},
    outputs={"poses_odometry": "poses_odometry", "poses_optimized": "poses_optimized",
             "loop_closures": "loop_closures", "report": "posegraph_report"},
    params=PosegraphParams,
    partition=Partitioning.SINGLE,
    compute="stages.posegraph.compute:compute",
    optional_inputs=frozenset({"survey", "odometry", "span_edges", "prior"}),
    settings_keys=frozenset({"map_drives", "eval_drives", "held_poses"}),  # held_poses: incremental
)
