"""Schema registry. Every field carries ``unit`` and, where it has one, ``frame`` metadata."""
from __future__ import annotations

import pyarrow as pa

SCHEMAS: dict[str, pa.Schema] = {}


def field(name: str, type_: pa.DataType, unit: str = "", frame: str = "", doc: str = "",
          nullable: bool = False) -> pa.Field:
    meta = {k: v for k, v in {"unit": unit, "frame": frame, "doc": doc}.items() if v}
    return pa.field(name, type_, nullable=nullable, metadata=meta or None)


def register(name: str, doc: str, *fields: pa.Field, row_group_key: str | None = None) -> pa.Schema:
    """``row_group_key``: a column whose rows are read a few values at a time (scans by ``scan_id``); the store
    ends its files' row groups where that column changes (``pipeline.store.row_group_bounds``)."""
    meta = {"dataset": name, "doc": doc, **({"row_group_key": row_group_key} if row_group_key else {})}
    if row_group_key and row_group_key not in [f.name for f in fields]:
        raise ValueError(f"schema {name!r}: row_group_key {row_group_key!r} is not one of its fields")
    schema = pa.schema(list(fields), metadata=meta)
    SCHEMAS[name] = schema
    return schema


def schema_of(name: str) -> pa.Schema:
    from pipeline.errors import UnknownNameError

    if name not in SCHEMAS:
        raise UnknownNameError(f"no schema named {name!r}; known: {', '.join(sorted(SCHEMAS))}")
    return SCHEMAS[name]


# Import the modules that register schemas (kept small, one per data-flow step).
from schemas import landmarks, products, raw, tiles, trajectory  # noqa: E402,F401 - importing registers them
