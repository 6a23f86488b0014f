"""Arrow schemas of every intermediate and product, with units and frames in field metadata.

``SCHEMAS[name]`` is the schema of dataset ``name`` (the catalog refers to these names). Partition columns
(drive, chunk, tile_i, tile_j) are part of the schema; the store writes them as hive directories.
"""
from __future__ import annotations

from schemas.registry import SCHEMAS, field, schema_of  # noqa: F401 - the package's public names
