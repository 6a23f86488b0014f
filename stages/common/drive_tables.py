"""Row selection by drive on Arrow tables (map layers are built from the workflow's map drives only)."""
from __future__ import annotations

import pyarrow as pa
import pyarrow.compute as pc


def select_drives(table: pa.Table, drives: list[str]) -> pa.Table:
    """Rows whose ``drive`` is in ``drives``; every row when ``drives`` is empty (no roles declared)."""
    return table.filter(pc.is_in(table["drive"], pa.array(drives, pa.string()))) if drives else table
