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


def test_survey_anchors_in_parallel_processes_equal_the_serial_ones(tiny_sync):
    """The pose graph's survey anchors (ground GICP and marking matches) of the tiny map drive, computed in the
    stage's process and in a process pool in blocks of 3 keyframes: the same matches."""
    import numpy as np

    from pipeline.declare import PartitionKey
    from pipeline.execute import _context, _task_spec
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow
    from stages.posegraph.compute import read_drive_inputs, scan_loader
    from stages.posegraph.core import base_problem
    from stages.posegraph.graph import optimize
    from stages.posegraph.survey_anchor import survey_anchor_callback

    root, _ = tiny_sync
    plan = make_plan(load_workflow(REPO / "workflows" / "tiny.yaml"), root)
    sp = plan.stages["posegraph"]
    ctx = _context(_task_spec(plan, sp), PartitionKey(), root / "tmp" / "test-anchors", {})
    drives, _ = read_drive_inputs(ctx)
    survey = ctx.inputs.read("survey", columns=["east_m", "north_m", "up_m", "intensity"])
    pts = np.column_stack([survey[c].to_numpy() for c in ("east_m", "north_m", "up_m")])
    problem, offsets = base_problem(drives, ctx.params)
    poses = optimize(problem)
    results = []
    for params in (ctx.params.model_copy(update={"parallel_min_items": 10_000}),
                   ctx.params.model_copy(update={"parallel_min_items": 2, "survey_marking_block": 3})):
        matches: list = []
        survey_anchor_callback(drives, scan_loader(ctx), pts, params, matches,
                               survey_intensity=survey["intensity"].to_numpy(),
                               feature_load=scan_loader(ctx, ("intensity", "ring")))(poses, offsets)
        results.append(matches)
    serial, parallel = results
    assert len(serial) == len(parallel) > 3
    assert sum(m.horizontal is not None and m.horizontal.accepted for m in serial) > 0
    for a, b in zip(serial, parallel):
        assert (a.i, a.accepted, a.horizontal.accepted) == (b.i, b.accepted, b.horizontal.accepted)
        np.testing.assert_allclose(a.T_map_vehicle, b.T_map_vehicle, atol=1e-6)
        np.testing.assert_allclose(a.horizontal.shift_en_m, b.horizontal.shift_en_m, atol=1e-6)
