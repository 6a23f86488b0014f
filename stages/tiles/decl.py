"""Declaration of the tiles stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages.tiles.params import TilesParams

STAGE = StageDecl(
    name="tiles",
    summary="Publish the corner map and marking rasters as an immutable, checksummed map version (vNNNN + LATEST).",
    code_version="2",
    inputs={"corner_map": "corner_map", "raster": "marking_raster", "rasters": "marking_rasters",
            "poses": "poses_optimized", "drive_info": "drive_info"},
    optional_inputs=frozenset({"raster", "rasters"}),
    outputs={"published": "map_tiles"},
    params=TilesParams,
    partition=Partitioning.SINGLE,
    compute="stages.tiles.compute:compute",
    cli="stages.tiles.cli",
)
