"""Declaration of the tiles stage (imports nothing heavy)."""
from pipeline.declare import Partitioning, StageDecl
from stages import code_version
from stages.tiles.params import TilesParams

STAGE = StageDecl(
    name="tiles",
    summary="Publish the corner map and marking rasters as an immutable, checksummed map version (vNNNN + LATEST).",
    # the published layout and the vectorizer it runs are part of what it writes
    code_version=code_version("2", "tiles", "mapformat"),
    inputs={"corner_map": "corner_map", "raster": "marking_raster", "rasters": "marking_rasters",
            "poses": "poses_optimized", "drive_info": "drive_info"},
    optional_inputs=frozenset({"raster", "rasters"}),
    outputs={"published": "map_tiles"},
    params=TilesParams,
    partition=Partitioning.SINGLE,
    compute="stages.tiles.compute:compute",
    cli="stages.tiles.cli",
    settings_keys=frozenset({"tile_size_m", "map_name", "enu_origin", "map_drives"}),
)
