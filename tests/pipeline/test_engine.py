"""Engine oracles on LiDAR-free toy stages: skip on rerun, param change re-runs downstream only,
sync vs distributed equality, kill -9 then resume, and all workflow mistakes reported at once."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pyarrow as pa
import pytest
import yaml

from tests.pipeline.toy_stages import EXTRA

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def toy_stages(monkeypatch):
    from pipeline.registry import load_stages

    monkeypatch.setenv("CORNERMAP_EXTRA_STAGES", EXTRA)
    monkeypatch.setenv("PYTHONPATH", str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    load_stages.cache_clear()
    yield
    load_stages.cache_clear()


def write_toy(tmp: Path, *, params: dict | None = None, stages=("numbers", "squares", "total")) -> Path:
    (tmp / "catalog").mkdir(exist_ok=True)
    (tmp / "catalog" / "toy.yaml").write_text(yaml.safe_dump({"datasets": {
        "toy_numbers": {"schema": "tests.pipeline.toy_stages:NUMBERS", "partitioning": ["drive", "chunk"]},
        "toy_squares": {"schema": "tests.pipeline.toy_stages:SQUARES", "partitioning": ["drive", "chunk"]},
        "toy_notes": {"kind": "artifacts"},
        "toy_total": {"schema": "tests.pipeline.toy_stages:TOTAL"},
    }}))
    for d in ("d0", "d1"):
        (tmp / d).mkdir(exist_ok=True)
        (tmp / d / "drive.yaml").write_text(f"name: {d}\n")
    wf = {"name": "toy", "catalog": [str(tmp / "catalog")], "root": str(tmp / "root"), "scheduler": "sync",
          "drives": [{"name": "d0", "path": str(tmp / "d0" / "drive.yaml")},
                     {"name": "d1", "path": str(tmp / "d1" / "drive.yaml")}],
          "stages": list(stages), "params": params or {}}
    path = tmp / "toy.yaml"
    path.write_text(yaml.safe_dump(wf))
    return path


def run(path: Path, **kw):
    from pipeline.api import execute_workflow

    return execute_workflow(path, root=kw.pop("root", None), scheduler=kw.pop("scheduler", None),
                            only=kw.pop("only", None), dry_run=False, quiet=True, **kw)


def read_output(root: Path, dataset: str) -> pa.Table:
    import pyarrow.parquet as pq

    [fp_dir] = [p for p in (root / "datasets" / dataset).iterdir() if (p / "_manifest.json").exists()]
    m = json.loads((fp_dir / "_manifest.json").read_text())
    tables = [pq.read_table(fp_dir / f["path"]) for f in m["files"]]
    return pa.concat_tables(tables).sort_by([(c, "ascending") for c in tables[0].column_names])


def decisions(result) -> dict[str, str]:
    return {k: v["decision"] for k, v in result["summary"].items()}


def test_stage_context_reads_what_the_run_committed(tmp_path):
    """The public stage context (benches call a stage's functions with it) sees the plan's params and reads the
    committed input; a stage outside the plan is a named error."""
    from pipeline.api import stage_context
    from pipeline.errors import UnknownNameError
    from pipeline.plan import make_plan

    path = write_toy(tmp_path, params={"total": {"scale": 3.0}})
    plan = run(path)["plan"]
    ctx = stage_context(make_plan(plan.workflow, plan.root), "total", tmp_path / "scratch")
    assert ctx.params.scale == 3.0
    got = ctx.inputs.read("squares")
    want = read_output(plan.root, "toy_squares")
    assert sorted(got["value"].to_pylist()) == sorted(want["value"].to_pylist()) and got.num_rows > 0
    with pytest.raises(UnknownNameError, match="did you mean 'total'"):
        stage_context(plan, "totl", tmp_path / "scratch")


def test_second_run_skips_and_param_change_reruns_downstream(tmp_path):
    path = write_toy(tmp_path)
    assert decisions(run(path)) == {"numbers": "ran", "squares": "ran", "total": "ran"}
    assert decisions(run(path)) == {"numbers": "skipped", "squares": "skipped", "total": "skipped"}
    path = write_toy(tmp_path, params={"squares": {"offset": 1.0}})
    assert decisions(run(path)) == {"numbers": "skipped", "squares": "ran", "total": "ran"}
    path = write_toy(tmp_path, params={"squares": {"offset": 1.0}, "total": {"scale": 2.0}})
    assert decisions(run(path)) == {"numbers": "skipped", "squares": "skipped", "total": "ran"}
    committed = lambda ds: len(list((tmp_path / "root" / "datasets" / ds).glob("*/_manifest.json")))  # noqa: E731
    assert (committed("toy_numbers"), committed("toy_squares"), committed("toy_total")) == (1, 2, 3)


def test_manifest_records_provenance_and_partitions(tmp_path):
    path = write_toy(tmp_path)
    run(path)
    root = tmp_path / "root"
    [fp_dir] = list((root / "datasets" / "toy_squares").iterdir())
    m = json.loads((fp_dir / "_manifest.json").read_text())
    assert m["rows"] == 800 and len(m["partitions"]) == 8
    assert m["params"] == {"offset": 0.0, "sleep_s": 0.0} and m["code_version"] == "1"
    assert m["inputs"]["numbers"]["dataset"] == "toy_numbers"
    assert all(len(f["sha256"]) == 64 and "drive=" in f["path"] and "chunk=" in f["path"] for f in m["files"])
    [notes] = list((root / "datasets" / "toy_notes").iterdir())
    assert sorted(p.name for p in (notes / "artifacts").iterdir()) == sorted(m["partitions"])


def test_sync_and_distributed_local_cluster_give_equal_tables(tmp_path):
    distributed = pytest.importorskip("distributed")
    path = write_toy(tmp_path)
    run(path, root=tmp_path / "sync")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None) as cl:
        run(path, root=tmp_path / "dist", scheduler=cl.scheduler_address)
    for ds in ("toy_numbers", "toy_squares", "toy_total"):
        assert read_output(tmp_path / "sync", ds).equals(read_output(tmp_path / "dist", ds)), ds


def test_processes_scheduler_equals_sync(tmp_path):
    path = write_toy(tmp_path)
    run(path, root=tmp_path / "sync")
    run(path, root=tmp_path / "proc", scheduler="processes")
    assert read_output(tmp_path / "sync", "toy_squares").equals(read_output(tmp_path / "proc", "toy_squares"))


def test_processes_pool_starts_one_native_thread_per_process(tmp_path, monkeypatch):
    """A process per core must not also start an OpenMP/BLAS thread per core; a user's setting is kept and the
    parent's environment is left as it was."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")
    run(write_toy(tmp_path), root=tmp_path / "proc", scheduler="processes")
    notes = [p.read_text() for p in (tmp_path / "proc" / "datasets" / "toy_notes").glob("*/artifacts/*/note.txt")]
    assert len(notes) == 8 and all("OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=3" in n for n in notes), notes
    assert "OMP_NUM_THREADS" not in os.environ and os.environ["OPENBLAS_NUM_THREADS"] == "3"


def test_sigkill_mid_stage_then_rerun_equals_uninterrupted(tmp_path):
    path = write_toy(tmp_path, params={"squares": {"sleep_s": 0.4}})
    ref = write_toy(tmp_path / "ref" if (tmp_path / "ref").mkdir() is None else tmp_path,
                    params={"squares": {"sleep_s": 0.0}})
    run(ref, root=tmp_path / "ref_root")
    env = dict(os.environ)
    cmd = [sys.executable, "-m", "mapservice", "run", str(path), "--scheduler", "sync", "--quiet"]
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, start_new_session=True)
    squares_root = tmp_path / "root" / "datasets" / "toy_squares"
    deadline = time.time() + 60
    while time.time() < deadline:  # wait until some but not all squares partitions are committed
        parts = list(squares_root.glob("*/_parts/*.json"))
        if len(parts) >= 2:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    committed = list(squares_root.glob("*/_manifest.json"))
    assert not committed, "the stage must not be committed after a kill in its middle"
    # A reader during the kill sees nothing of the partial stage.
    from pipeline.store import read_manifest

    assert all(read_manifest(p) is None for p in squares_root.iterdir())
    result = run(path)
    assert result["summary"]["squares"]["decision"] == "ran"
    a, b = read_output(tmp_path / "root", "toy_squares"), read_output(tmp_path / "ref_root", "toy_squares")
    assert a.equals(b)
    assert read_output(tmp_path / "root", "toy_total").equals(read_output(tmp_path / "ref_root", "toy_total"))


def _pool_processes(pid: int) -> list[int]:
    """The multiprocessing pool processes ``pid`` started (its children running ``spawn_main``)."""
    try:
        children = psutil.Process(pid).children()
    except psutil.NoSuchProcess:
        return []
    out = []
    for child in children:
        try:
            if "spawn_main" in " ".join(child.cmdline()):
                out.append(child.pid)
        except psutil.Error:  # gone meanwhile
            continue
    return out


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _start_mid_squares(tmp_path) -> tuple[subprocess.Popen, list[int], Path]:
    """A toy run on the local process pool, stopped in the middle of squares (each partition sleeps 30 s): the
    process and its pool processes."""
    path = write_toy(tmp_path, params={"squares": {"sleep_s": 30.0}})
    cmd = [sys.executable, "-m", "mapservice", "run", str(path), "--scheduler", "local", "--workers", "2", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=REPO, start_new_session=True, stderr=subprocess.PIPE, text=True)
    numbers = tmp_path / "root" / "datasets" / "toy_numbers"
    deadline = time.time() + 90
    pool: list[int] = []
    while time.time() < deadline and proc.poll() is None:
        pool = _pool_processes(proc.pid)
        if len(pool) >= 2 and list(numbers.glob("*/_manifest.json")):
            break
        time.sleep(0.1)
    assert proc.poll() is None and len(pool) >= 2, "the run should be in squares with its pool started"
    time.sleep(1.0)  # the squares partitions are sleeping in the pool processes
    return proc, pool, tmp_path / "root" / "datasets" / "toy_squares"


def _gone_within(pids: list[int], seconds: float) -> list[int]:
    deadline = time.time() + seconds
    while time.time() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.1)
    return [p for p in pids if _alive(p)]


def test_sigkill_of_the_engine_alone_ends_its_pool_processes(tmp_path):
    """A job scheduler's timeout or the OOM killer kills the engine's process, not its pool: the pool processes must
    not live on (they used to wait forever in a queue read, holding their memory)."""
    proc, pool, squares = _start_mid_squares(tmp_path)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()  # not communicate(): pool processes that outlive it hold its stderr pipe open
    proc.stderr.close()
    try:
        left = _gone_within(pool, 10.0)
        assert not left, f"pool processes {left} outlived their engine"
        assert not list(squares.glob("*/_manifest.json"))
    finally:  # whatever outlived it (its own session's group)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_sigterm_ends_the_run_with_one_line_exit_143_and_no_pool_left(tmp_path):
    proc, pool, squares = _start_mid_squares(tmp_path)
    t0 = time.time()
    os.kill(proc.pid, signal.SIGTERM)  # the engine's process only, as a job scheduler would
    try:
        _, err = proc.communicate(timeout=30)
        assert not _gone_within(pool, 5.0)
    finally:  # whatever outlived it (its own session's group)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    from mapservice.cli import EXIT_TERMINATED

    assert proc.returncode == EXIT_TERMINATED, err
    assert time.time() - t0 < 20, "a SIGTERM must not wait for the sleeping partitions (30 s)"
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("terminated: SIGTERM"), err
    assert not list(squares.glob("*/_manifest.json")), "a stopped stage is not committed"
    result = run(write_toy(tmp_path, params={"squares": {"sleep_s": 0.0}}))  # and the next run goes on
    assert result["summary"]["numbers"]["decision"] != "ran" and result["summary"]["squares"]["decision"] == "ran"


def test_three_mistakes_reported_at_once_exit_1_no_traceback(tmp_path):
    path = write_toy(tmp_path, params={"numbers": {"n_chunk": 3}}, stages=("numbers", "squarez", "total"))
    env = dict(os.environ)
    out = subprocess.run([sys.executable, "-m", "mapservice", "run", str(path)], env=env, cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stderr
    err = out.stderr
    assert "Traceback" not in err
    assert "unknown stage 'squarez'" in err and "did you mean 'squares'" in err
    assert "'n_chunk'" in err and "did you mean 'n_chunks'" in err
    assert "toy_squares" in err  # total needs a dataset no stage produces
    assert err.count("\n  - ") >= 3


def test_dry_run_prints_order_and_decisions(tmp_path):
    path = write_toy(tmp_path)
    out = subprocess.run([sys.executable, "-m", "mapservice", "run", str(path), "--dry-run"], cwd=REPO,
                         capture_output=True, text=True, timeout=120, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stderr
    text = out.stdout
    assert text.index("numbers") < text.index("squares") < text.index("total")
    assert "dynamic" in text and "run" in text


def test_schema_mismatch_lists_every_bad_column():
    from pipeline.errors import SchemaMismatchError
    from pipeline.store import conform_table
    from tests.pipeline.toy_stages import NUMBERS

    bad = pa.table({"drive": [1], "value": ["x"], "extra": [0]})
    with pytest.raises(SchemaMismatchError) as info:
        conform_table(bad, NUMBERS, "test")
    msg = str(info.value)
    assert "'drive'" in msg and "'chunk'" in msg and "'value'" in msg and "'extra'" in msg


@pytest.mark.parametrize("scheduler", ["threads", "processes"])
def test_downstream_partitions_start_before_the_upstream_stage_ends(tmp_path, scheduler):
    """One dataflow for the workflow: squares of drive d0 run while numbers of drive d1 still sleeps, and the
    result equals a stage-by-stage (sync) run."""
    params = {"numbers": {"slow_drive": "d1", "sleep_s": 3.0}}
    path = write_toy(tmp_path, params=params)
    out = run(path, root=tmp_path / "flow", scheduler=scheduler)
    s = out["summary"]
    assert s["squares"]["started_s"] < s["numbers"]["ended_s"] - 1.0, s
    assert s["total"]["started_s"] >= s["squares"]["ended_s"]  # a single stage waits for its producer's commit
    assert all(10 < s[n]["peak_rss_mb"] < 4096 for n in ("numbers", "squares", "total")), s  # a Python process
    run(path, root=tmp_path / "sync", scheduler="sync")
    for ds in ("toy_numbers", "toy_squares", "toy_total"):
        assert read_output(tmp_path / "flow", ds).equals(read_output(tmp_path / "sync", ds))
    again = run(path, root=tmp_path / "flow", scheduler=scheduler)
    assert decisions(again) == {"numbers": "skipped", "squares": "skipped", "total": "skipped"}
