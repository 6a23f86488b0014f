"""In-memory stand-ins for stage tests: run a stage's compute on Arrow tables without a store."""
from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

import pyarrow as pa
import pyarrow.compute as pc

from pipeline.catalog import PARTITION_COLUMNS as _PARTITION_COLUMNS
from pipeline.declare import InputReader, Params, PartitionKey, StageContext
from pipeline.errors import UnknownNameError


class MemoryInputReader(InputReader):
    """Serves tables from memory; ``partition=`` filters on the partition columns present in the table."""

    def __init__(self, tables: Mapping[str, pa.Table], metadata: Mapping[str, dict] | None = None,
                 artifact_dirs: Mapping[str, Path] | None = None):
        self._tables = dict(tables)
        self._metadata = dict(metadata or {})
        self._artifacts = dict(artifact_dirs or {})

    def has(self, arg: str) -> bool:
        return arg in self._tables or arg in self._artifacts

    def read(self, arg, *, partition=None, columns=None, filters=None) -> pa.Table:
        if arg not in self._tables:
            raise UnknownNameError(f"no input {arg!r} in this test context; have {sorted(self._tables)}")
        table = self._tables[arg]
        if partition is not None:
            for name, value in partition.as_dict().items():
                if name in table.column_names:
                    table = table.filter(pc.equal(table[name], value))
        if filters is not None:
            table = table.filter(filters)
        return table.select(columns) if columns else table

    def read_in(self, arg, column, values, *, partition=None, columns=None) -> pa.Table:
        table = self.read(arg, partition=partition)
        table = table.filter(pc.is_in(table[column], value_set=pa.array(list(values), table.schema.field(column).type)))
        return table.select(columns) if columns else table

    def partitions(self, arg: str) -> list[PartitionKey]:
        table = self._tables[arg]
        cols = [c for c in _PARTITION_COLUMNS if c in table.column_names]
        if not cols:
            return [PartitionKey()]
        rows = table.select(cols).group_by(cols).aggregate([]).to_pylist()
        return sorted(PartitionKey(**row) for row in rows)

    def metadata(self, arg: str) -> dict[str, Any]:
        return dict(self._metadata.get(arg, {}))

    def artifact_dir(self, arg: str, partition: PartitionKey | None = None) -> Path:
        return self._artifacts[arg]


def make_context(stage: str, params: Params, tables: Mapping[str, pa.Table] | None = None, *,
                 partition: PartitionKey | None = None, drives: Mapping[str, Path] | None = None,
                 settings: Mapping[str, Any] | None = None, metadata: Mapping[str, dict] | None = None,
                 input_artifacts: Mapping[str, Path] | None = None, outputs: tuple[str, ...] = (),
                 workdir: Path | None = None) -> StageContext:
    if workdir is None:  # removed when the process exits (tests that pass no folder leave nothing in /tmp)
        workdir = tempfile.mkdtemp(prefix=f"cornermap-{stage}-")
        atexit.register(shutil.rmtree, workdir, True)
    workdir = Path(workdir)
    base_settings = {"map_name": "test", "enu_origin": None, "tile_size_m": None, "map_drives": [],
                     "eval_drives": [], "root": str(workdir), "references": {}}
    base_settings.update(settings or {})
    return StageContext(
        stage=stage, partition=partition or PartitionKey(), params=params,
        inputs=MemoryInputReader(tables or {}, metadata, input_artifacts), drives=dict(drives or {}),
        settings=base_settings, scratch_dir=workdir / "scratch",
        artifact_dirs={key: workdir / "artifacts" / key for key in outputs},
    )
