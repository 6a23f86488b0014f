"""The published pose-graph solution an incremental solve holds fixed: the ``poses_optimized`` rows, loop rows and
report files of the dataset the workflow's ``held_poses`` setting names (``{fingerprint, version}``, written by
``cornermap rebuild`` from its LATEST version's manifest), read through the store's verified reader."""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.errors import ConfigError
from schemas.registry import schema_of
from stages.common.records import pose_matrices
from stages.posegraph.factors.drive import DriveInput


@dataclass
class HeldSolution:
    version: int | None
    drives: set[str]  # map drives whose published rows are held (their scans as the drive input's)
    table: pa.Table  # poses_optimized rows of those drives
    loops: pa.Table  # loop_closures rows between held drives
    report_dir: Path | None
    metadata: dict

    def rows(self, drive: str) -> pa.Table:
        return self.table.filter(pc.equal(self.table["drive"], drive))

    def poses_T(self, drive: str) -> np.ndarray:
        return pose_matrices(self.rows(drive))

    def loop_rows(self) -> list[dict]:
        return self.loops.to_pylist()

    def copy_report_file(self, name: str, out_dir: Path) -> bool:
        """Copy the published report's file ``name`` (a held drive's trajectory) into ``out_dir``; False when absent."""
        src = None if self.report_dir is None else self.report_dir / name
        if src is None or not src.is_file():
            return False
        shutil.copyfile(src, Path(out_dir) / name)
        return True


def read_held(root: str | Path, spec: dict, drives: list[DriveInput]) -> HeldSolution:
    """The held solution for ``drives``: a drive is held when the dataset has its rows for exactly its scans."""
    from pipeline.errors import DatasetIOError
    from pipeline.reader import StoreInputReader

    fp = spec.get("fingerprint") if isinstance(spec, dict) else None
    if not isinstance(fp, str) or not fp:
        raise ConfigError("workflow setting held_poses", [f"expected {{fingerprint, version}}, got {spec!r}"])
    reader = StoreInputReader(Path(root), {"poses": ("poses_optimized", fp), "loops": ("loop_closures", fp),
                                           "report": ("posegraph_report", fp)},
                              {"poses": schema_of("poses_optimized"), "loops": schema_of("loop_closures"),
                               "report": None})
    if not reader.has("poses"):
        raise DatasetIOError(f"held_poses: the published solution poses_optimized/{fp[:16]} (version "
                             f"{spec.get('version')}) has no committed data under {root}; hint: run `cornermap "
                             "rebuild --full` (gc may have removed it)")
    table = reader.read("poses")
    names = set()
    for d in drives:
        rows = table.filter(pc.equal(table["drive"], d.name))
        if rows.num_rows == d.n and np.array_equal(rows["scan_id"].to_numpy(), d.scan_ids):
            names.add(d.name)
    table = table.filter(pc.is_in(table["drive"], pa.array(sorted(names), pa.string())))
    loops = reader.read("loops") if reader.has("loops") else schema_of("loop_closures").empty_table()
    if loops.num_rows:
        keep = pc.and_(pc.is_in(loops["drive_a"], pa.array(sorted(names), pa.string())),
                       pc.is_in(loops["drive_b"], pa.array(sorted(names), pa.string())))
        loops = loops.filter(keep)
    try:
        report_dir = reader.artifact_dir("report")
    except DatasetIOError:
        report_dir = None
    meta = reader.metadata("poses")
    return HeldSolution(spec.get("version"), names, table, loops, report_dir, meta)
