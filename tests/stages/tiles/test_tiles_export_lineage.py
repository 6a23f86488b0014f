"""An export reads exactly the datasets its version records (mapformat.lineage), never the newest of a name.

A root holds map A's committed datasets; a second map B is then built in the same root from a drive of the same
name with other scans, committed later. Exporting A again gives the same bytes; the export before this change
took the newest ``scans_raw`` and wrote B's scans into A's point cloud.
"""
from __future__ import annotations

import datetime as dt
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mapformat.export import export_map
from mapformat.lineage import VersionLineage
from mapformat.loader import open_map
from pipeline.errors import DatasetIOError
from pipeline.fingerprint import file_sha256
from pipeline.store import dataset_dir
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import (
    building_corners,
    buildings,
    city_context,
    corner_table,
    drive_info_table,
    drive_path,
    poses_table,
)

DRIVE = "drive_a"


def _commit(root: Path, dataset: str, fp: str, stage: str, table: pa.Table, inputs: dict, when: str) -> None:
    """A committed dataset as the engine writes it (pipeline.execute.commit_stage): one file of ``DRIVE``."""
    d = dataset_dir(root, dataset, fp)
    (d / f"drive={DRIVE}").mkdir(parents=True)
    path = d / f"drive={DRIVE}" / "part-0.parquet"
    pq.write_table(table, path)
    manifest = {"dataset": dataset, "stage": stage, "fingerprint": fp, "inputs": inputs,
                "files": [{"path": f"drive={DRIVE}/part-0.parquet", "rows": table.num_rows,
                           "sha256": file_sha256(path), "partition": {"drive": DRIVE}}],
                "committed_utc": when}
    (d / "_manifest.json").write_text(json.dumps(manifest))


def _scans(stamp0_ns: int, wall_east_m: float, seed: int, n_scans: int = 40) -> pa.Table:
    """Lidar-frame scans (identity extrinsics: the vehicle frame): road points at z = 0 and a wall."""
    rng = np.random.default_rng(seed)
    cols: dict[str, list] = {k: [] for k in ("scan_id", "stamp_ns", "x_m", "y_m", "z_m", "intensity",
                                             "time_offset_s")}
    for k in range(n_scans):
        ground = np.column_stack([rng.uniform(-15, 15, 1500), rng.uniform(-15, 15, 1500), np.zeros(1500)])
        wall = np.column_stack([np.full(500, wall_east_m), rng.uniform(-10, 10, 500), rng.uniform(0.2, 5, 500)])
        pts = np.vstack([ground, wall])
        cols["scan_id"] += [k] * len(pts)
        cols["stamp_ns"] += [stamp0_ns + k * 100_000_000] * len(pts)
        for c, v in zip(("x_m", "y_m", "z_m"), pts.T):
            cols[c] += v.tolist()
        cols["intensity"] += rng.uniform(0, 100, len(pts)).tolist()
        cols["time_offset_s"] += rng.uniform(0, 0.09, len(pts)).tolist()
    types = {"scan_id": pa.int64(), "stamp_ns": pa.int64(), "time_offset_s": pa.float32()}
    return pa.table({k: pa.array(v, types.get(k, pa.float32())) for k, v in cols.items()})


def build(root: Path, tag: str, map_name: str, wall_east_m: float, when: str) -> None:
    """What a build of ``map_name`` from drive ``DRIVE`` leaves: ingest and pose graph outputs, a published version."""
    ingest_fp, poses_fp = f"{tag}-drive_info", f"{tag}-poses"
    poses = poses_table(drive_path(), DRIVE)
    stamp0 = int(poses["stamp_ns"][0].as_py())
    _commit(root, "drive_info", ingest_fp, "ingest", drive_info_table(DRIVE), {}, when)
    _commit(root, "scans_raw", ingest_fp, "ingest", _scans(stamp0, wall_east_m, seed=len(tag)), {}, when)
    _commit(root, "poses_optimized", poses_fp, "posegraph", poses,
            {"scans": {"dataset": "scans_raw", "fingerprint": ingest_fp},
             "drive_info": {"dataset": "drive_info", "fingerprint": ingest_fp}}, when)
    xy, dirs, _ = building_corners(buildings())
    ctx = city_context(root, corner_table(xy, dirs, seed=3), fingerprint=tag, map_name=map_name)
    compute(ctx)


@pytest.fixture(scope="module")
def root_with_map_a(tmp_path_factory):
    root = tmp_path_factory.mktemp("lineage")
    build(root, "A", "city", wall_east_m=8.0, when="2026-01-01T00:00:00+00:00")
    return root


def _tree_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_export_reads_its_own_version_after_another_build_in_the_same_root(root_with_map_a, tmp_path):
    root = root_with_map_a
    reader = open_map(root / "maps" / "city")
    before = tmp_path / "before"
    export_map(reader, "autoware", before, root=root)
    # map B: a drive of the same name, other scans (the wall on the other side), committed later
    build(root, "B", "cityb", wall_east_m=-8.0, when="2026-06-01T00:00:00+00:00")
    after = tmp_path / "after"
    export_map(open_map(root / "maps" / "city"), "autoware", after, root=root)
    assert _tree_bytes(after) == _tree_bytes(before)
    doc = json.loads((after / "cornermap_export.json").read_text())
    assert doc["inputs"] == {"poses_optimized": "A-poses", "drive_info": "A-drive_info", "scans_raw": "A-drive_info"}
    other = tmp_path / "b"
    export_map(open_map(root / "maps" / "cityb"), "autoware", other, root=root)
    assert json.loads((other / "cornermap_export.json").read_text())["inputs"]["scans_raw"] == "B-drive_info"
    assert _tree_bytes(other)["pointcloud_map_metadata.yaml"] != b"" and \
        _tree_bytes(other) != _tree_bytes(after)  # B's scans are B's


def test_the_lineage_follows_recorded_inputs_and_siblings(root_with_map_a):
    reader = open_map(root_with_map_a / "maps" / "city")
    lineage = VersionLineage(root_with_map_a, reader.manifest, "v1")
    assert lineage.find("poses_optimized").fingerprint == "A-poses"
    assert lineage.find("scans_raw", DRIVE).fingerprint == "A-drive_info"
    assert [c.fingerprint for c in lineage.candidates("scans_raw")] == ["A-drive_info"]
    with pytest.raises(DatasetIOError, match="no committed scans_raw of drive 'nope'"):
        lineage.find("scans_raw", "nope")


def test_a_removed_input_is_named_in_one_line(root_with_map_a, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(root_with_map_a, root)
    shutil.rmtree(dataset_dir(root, "scans_raw", "A-drive_info"))
    shutil.rmtree(dataset_dir(root, "drive_info", "A-drive_info"))
    with pytest.raises(DatasetIOError) as exc:
        export_map(open_map(root / "maps" / "city"), "autoware", tmp_path / "aw", root=root)
    msg = str(exc.value)
    assert "\n" not in msg and "drive_info A-drive_info" in msg and "removed by gc" in msg, msg
    assert not (tmp_path / "aw").exists()  # nothing written before the inputs are known


def test_a_damaged_input_file_is_refused(root_with_map_a, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(root_with_map_a, root)
    part = dataset_dir(root, "poses_optimized", "A-poses") / f"drive={DRIVE}" / "part-0.parquet"
    table = pq.read_table(part)
    pq.write_table(table.slice(0, table.num_rows - 1), part)
    with pytest.raises(Exception, match="sha256|checksum|changed"):
        export_map(open_map(root / "maps" / "city"), "autoware", tmp_path / "aw", root=root)


def test_a_version_that_records_no_inputs_is_refused(root_with_map_a):
    reader = open_map(root_with_map_a / "maps" / "city")
    with pytest.raises(DatasetIOError, match="records no inputs"):
        VersionLineage(root_with_map_a, {**reader.manifest, "inputs": {}}, "v1")


def test_dates_do_not_choose(root_with_map_a, tmp_path):
    """The newest committed scans of the drive are not A's; A's export still names A's."""
    stamp = dt.datetime.now(dt.timezone.utc).isoformat()
    root = tmp_path / "copy"
    shutil.copytree(root_with_map_a, root)
    _commit(root, "scans_raw", "Z-newest", "ingest", _scans(0, 3.0, seed=9), {}, stamp)
    lineage = VersionLineage(root, open_map(root / "maps" / "city").manifest, "v1")
    assert lineage.find("scans_raw", DRIVE).fingerprint == "A-drive_info"
