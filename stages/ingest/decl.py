"""Declaration of the ingest stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.ingest.params import IngestParams

STAGE = StageDecl(
    name="ingest",
    summary="Read a recorded drive (PCD / KITTI / nuScenes / LAS scans, GNSS/INS CSV, odometry, survey) into "
            "Parquet in the map's ENU frame",
    code_version=code_version("4", "ingest"),
    inputs={},
    outputs={"scans": "scans_raw", "scan_index": "scan_index", "gnss": "gnss_enu", "odometry": "odometry_raw",
             "poses_gnss": "poses_gnss", "poses_prior": "poses_prior", "drive_info": "drive_info",
             "survey": "survey_enu", "report": "ingest_report"},
    params=IngestParams,
    partition=Partitioning.PER_DRIVE,
    uses_drives=True,
    compute="stages.ingest.compute:compute",
    cli="stages.ingest.cli",
    preflight="stages.ingest.frame:preflight",
    settings_keys=frozenset({"enu_origin", "map_drives", "eval_drives"}),  # origin: first fix of the first drive
)
