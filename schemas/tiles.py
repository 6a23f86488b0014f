"""Schema of the tiles stage's output: one row per published (or reused) map version."""
import pyarrow as pa

from schemas.registry import field as f
from schemas.registry import register

register(
    "map_tiles", "The map version the tiles stage published (or reused) under ROOT/maps/NAME (docs/map-format.md).",
    f("map_name", pa.string()),
    f("version", pa.int32(), doc="N of the vNNNN directory"),
    f("path", pa.string(), doc="the version directory, relative to the output root (maps/NAME/vNNNN)"),
    f("n_tiles", pa.int32()), f("n_corners", pa.int64()),
    f("manifest_sha256", pa.string(), doc="sha256 of the version's manifest.json"),
)
