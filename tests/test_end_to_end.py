"""The tiny synthetic city through the whole workflow: simulate -> ingest -> odometry -> posegraph -> corners ->
cornermap -> markings -> tiles -> evaluate, on the synchronous scheduler and on a dask.distributed LocalCluster."""
from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pytest

REPO = Path(__file__).resolve().parents[1]


def run(root: Path, scheduler: str):
    from pipeline.cli import execute_workflow

    return execute_workflow(REPO / "workflows" / "tiny.yaml", root=root, scheduler=scheduler, only=None,
                            dry_run=False, quiet=True)


def committed_table(root: Path, dataset: str) -> pa.Table:
    import pyarrow.parquet as pq

    [d] = [p for p in (root / "datasets" / dataset).iterdir() if (p / "_manifest.json").exists()]
    m = json.loads((d / "_manifest.json").read_text())
    t = pa.concat_tables([pq.read_table(d / f["path"]) for f in m["files"]])
    return t.sort_by([(c, "ascending") for c in t.column_names if not pa.types.is_list(t.schema.field(c).type)])


@pytest.fixture(scope="module")
def tiny_sync(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_sync")
    return root, run(root, "sync")


def test_whole_workflow_publishes_a_map_and_evaluates_it(tiny_sync):
    root, result = tiny_sync
    assert all(v["decision"] == "ran" for v in result["summary"].values()), result["summary"]
    map_dir = root / "maps" / "tiny"
    latest = (map_dir / "LATEST").read_text().split()[0]
    manifest = json.loads((map_dir / latest / "manifest.json").read_text())
    assert manifest["n_corners"] > 0 and manifest["n_tiles"] > 0
    assert set(manifest["enu_origin"]) >= {"lat_deg", "lon_deg", "h_m"}
    [metrics] = list((root / "datasets" / "eval_report").glob("*/artifacts/*/metrics.json"))
    doc = json.loads(metrics.read_text())
    assert {"ekf", "mcl", "rtk_ins", "icp_dr"} <= set(doc["methods"])
    assert (metrics.parent / "report.html").stat().st_size > 10_000


def test_second_run_skips_every_stage(tiny_sync):
    root, _ = tiny_sync
    again = run(root, "sync")
    assert {v["decision"] for v in again["summary"].values()} == {"skipped"}


def test_distributed_local_cluster_gives_equal_tables(tiny_sync, tmp_path):
    distributed = pytest.importorskip("distributed")
    root, _ = tiny_sync
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None) as cl:
        run(tmp_path, cl.scheduler_address)
    for ds in ("scans_raw", "gnss_enu", "corners_per_scan", "marking_raster"):
        assert committed_table(root, ds).equals(committed_table(tmp_path, ds)), ds
    assert (tmp_path / "maps" / "tiny" / "LATEST").is_file()
