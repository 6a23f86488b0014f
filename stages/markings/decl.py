"""Declaration of the markings stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.markings.params import MarkingParams

STAGE = StageDecl(
    name="markings",
    summary="Road-marking rasters per tile (Kim et al. 2.1): elevation grid, traversable cells, adaptive "
            "intensity threshold; PNG + JSON sidecar per tile.",
    code_version=code_version("4", "markings"),
    inputs={"survey": "survey_enu", "scans": "scans_raw", "poses": "poses_optimized", "drive_info": "drive_info"},
    optional_inputs=frozenset({"survey", "scans", "poses", "drive_info"}),
    outputs={"raster": "marking_raster", "rasters": "marking_rasters"},
    params=MarkingParams,
    partition=Partitioning.PER_TILE,
    plan="stages.markings.compute:plan_tiles",
    compute="stages.markings.compute:compute",
    settings_keys=frozenset({"tile_size_m", "map_drives", "enu_origin"}),
)
