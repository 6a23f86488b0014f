"""Declaration of the evaluate stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.evaluate.params import EvaluateParams

STAGE = StageDecl(
    name="evaluate",
    summary="Localize evaluation drives on a published map: corner EKF, marking MCL, RTK/INS and ICP baselines.",
    code_version=code_version("11", "evaluate"),
    inputs={"map": "map_tiles", "corners": "corners_per_scan", "edges": "odometry_edges", "poses_gnss": "poses_gnss",
            "gnss": "gnss_enu", "odometry": "odometry_raw", "scans": "scans_raw", "drive_info": "drive_info",
            "reference": "poses_optimized", "prior": "poses_prior"},
    optional_inputs=frozenset({"reference", "gnss", "prior"}),
    outputs={"epochs": "eval_epochs", "report": "eval_report"},
    params=EvaluateParams,
    partition=Partitioning.PER_DRIVE,
    drive_role="eval",
    compute="stages.evaluate.compute:compute",
    cli="stages.evaluate.cli",
    settings_keys=frozenset({"references"}),
)
