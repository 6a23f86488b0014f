"""Peak RSS per task: the sampler sees memory a task holds briefly, the run summary carries it per stage, and a
workflow's memory budget names the stages over it."""
from __future__ import annotations

import time

import numpy as np
import pytest

from pipeline.memory import PeakRss, over_budget
from tests.pipeline.test_engine import run, toy_stages, write_toy  # noqa: F401 - toy_stages: the toy registry


def test_peak_rss_sees_a_short_lived_allocation():
    with PeakRss(interval_s=0.01) as before:
        pass
    with PeakRss(interval_s=0.01) as rss:
        block = np.ones(200 * 2**20 // 8)  # 200 MB, touched
        block[::512] += 1.0
        time.sleep(0.3)  # held for 30 sampling intervals: the sampler thread runs (numpy's fill may hold the GIL)
        del block
    assert rss.peak_mb >= before.peak_mb + 150, (before.peak_mb, rss.peak_mb)


def test_over_budget_names_each_stage_over_it_and_nothing_without_a_budget():
    summary = {"ingest": {"peak_rss_mb": 900.0}, "markings": {"peak_rss_mb": 2100.0}, "tiles": {"decision": "skip"}}
    lines = over_budget(summary, 1536)
    assert len(lines) == 1 and "'markings'" in lines[0] and "2100 MB" in lines[0] and "1536" in lines[0]
    assert over_budget(summary, None) == []


def test_a_run_over_the_workflows_memory_budget_names_its_stages(tmp_path, capsys):
    import yaml

    path = write_toy(tmp_path)
    spec = yaml.safe_load(path.read_text())
    path.write_text(yaml.safe_dump({**spec, "memory_budget_mb": 1.0}))  # every Python process is over 1 MB
    out = run(path, root=tmp_path / "r")
    err = capsys.readouterr().err
    for stage in ("numbers", "squares", "total"):
        assert out["summary"][stage]["peak_rss_mb"] > 1.0
        assert f"stage {stage!r} peaked at" in err, err
    path.write_text(yaml.safe_dump({**spec, "memory_budget_mb": None}))
    run(path, root=tmp_path / "r2")
    assert "peaked at" not in capsys.readouterr().err


@pytest.fixture
def trimmed_process():
    """This process, its heap just trimmed, and its resident bytes then (skipped where there is no C library)."""
    import ctypes.util

    import psutil

    from pipeline.memory import release_memory

    if not ctypes.util.find_library("c"):
        pytest.skip("no C library to trim")
    proc = psutil.Process()
    release_memory()
    return proc, proc.memory_info().rss


def test_release_memory_returns_a_finished_tasks_freed_heap_to_the_system(trimmed_process):
    """Many small objects live on the C heap; freed, they stay resident until the heap is trimmed. A worker that ran
    a heavy task must not carry that into the next one (pipeline.execute.run_partition calls this after each)."""
    from pipeline.memory import release_memory

    proc, before = trimmed_process
    blobs = [bytes(900) for _ in range(300_000)]  # ~300 MB in heap-sized pieces
    grown = proc.memory_info().rss - before
    del blobs
    release_memory()
    left = proc.memory_info().rss - before
    assert grown > 200 * 2**20
    assert left < 0.3 * grown


def test_malloc_is_relaxed_only_under_an_eager_trim_threshold_the_user_did_not_pair_with_an_mmap_threshold():
    import dask
    import distributed  # noqa: F401 - registers the distributed.* config

    from pipeline.memory import TASK_TRIM_THRESHOLD_BYTES, malloc_needs_relaxing

    dask_worker_env = {k: str(v) for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()}
    assert malloc_needs_relaxing(dask_worker_env)  # what a dask nanny starts its worker with
    assert malloc_needs_relaxing({"MALLOC_TRIM_THRESHOLD_": "65536"})
    assert not malloc_needs_relaxing({})  # glibc's dynamic thresholds: nothing to do
    assert not malloc_needs_relaxing({"MALLOC_TRIM_THRESHOLD_": "65536", "MALLOC_MMAP_THRESHOLD_": "131072"})
    assert not malloc_needs_relaxing({"MALLOC_TRIM_THRESHOLD_": str(TASK_TRIM_THRESHOLD_BYTES)})
    assert not malloc_needs_relaxing({"MALLOC_TRIM_THRESHOLD_": "lots"})


_FAULTS = """
import os, resource, numpy as np
from pipeline.memory import relax_malloc_trim
relaxed = relax_malloc_trim()
a = np.ones(262144); del a  # 2 MB
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(50):
    a = np.ones(262144); del a
print(relaxed, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_relaxed_malloc_reuses_a_freed_array_instead_of_faulting_in_fresh_pages(tmp_path):
    """Under dask's worker environment every 2 MB temporary is a fresh mmap: 512 page faults each time it is filled
    (measured 25,650 for 50 of them). After ``relax_malloc_trim`` the freed block is reused (measured 0)."""
    import ctypes.util
    import os
    import subprocess
    import sys
    from pathlib import Path

    if sys.platform != "linux" or not ctypes.util.find_library("c"):
        pytest.skip("glibc's mallopt only")
    root = str(Path(__file__).resolve().parents[2])
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")

    def faults(extra: dict) -> tuple[str, int]:
        out = subprocess.run([sys.executable, "-c", _FAULTS], env={**env, **extra}, capture_output=True, text=True,
                             check=True, cwd=tmp_path).stdout.split()
        return out[0], int(out[1])

    relaxed, relaxed_faults = faults({"MALLOC_TRIM_THRESHOLD_": "65536"})
    eager, eager_faults = faults({"MALLOC_TRIM_THRESHOLD_": "65536", "MALLOC_MMAP_THRESHOLD_": "131072"})
    assert (relaxed, eager) == ("True", "False")  # the user's own pair of thresholds is kept
    assert eager_faults > 40 * 512 * 0.9
    assert relaxed_faults < 0.05 * eager_faults


def test_a_task_scope_collects_its_cycles_then_freezes_the_survivors_only_when_no_other_task_runs():
    import gc
    import weakref

    from pipeline.memory import task_scope

    class Node:
        pass

    gc.unfreeze()
    try:
        with task_scope():
            a = Node()
            a.self = a  # a reference cycle the task leaves behind
            first = weakref.ref(a)
            del a
            with task_scope():  # another task of this process (a thread scheduler) ends while the first still runs
                pass
            assert gc.get_freeze_count() == 0
        assert first() is None  # collected at the end of its task
        assert gc.get_freeze_count() > 0  # the survivors: frozen once no task runs
        with task_scope():
            b = Node()
            b.self = b
            later = weakref.ref(b)
            del b
        assert later() is None  # a later task's cycle is still collected
    finally:
        gc.unfreeze()


def test_release_memory_keeps_the_freed_heap_below_its_threshold_and_trims_above(trimmed_process):
    from pipeline.memory import release_memory

    proc, before = trimmed_process
    blobs = [bytes(900) for _ in range(300_000)]  # ~300 MB in heap-sized pieces
    pin = [bytes(900) for _ in range(100)]  # allocated last: the heap's top stays in use, only a trim frees below it
    grown = proc.memory_info().rss - before
    del blobs
    release_memory(trim_above_mb=proc.memory_info().rss / 2**20 + 1000)  # far below the threshold: kept
    kept = proc.memory_info().rss - before
    release_memory(trim_above_mb=(before / 2**20) * 0.5)  # above it: trimmed
    left = proc.memory_info().rss - before
    del pin
    assert grown > 200 * 2**20
    assert kept > 0.7 * grown and left < 0.3 * grown, (grown, kept, left)


def test_a_task_knows_whether_it_ran_alone_in_its_process():
    """Alone: no other task running when it started, none started before it ended; a task overlapped by another
    (a thread scheduler) is not, and neither is the other."""
    import threading

    from pipeline.memory import task_scope

    with task_scope() as alone:
        pass
    assert alone.alone
    inner_started, outer_may_end = threading.Event(), threading.Event()
    scopes = {}

    def other():
        with task_scope() as s:
            scopes["inner"] = s
            inner_started.set()
            outer_may_end.wait(5)

    with task_scope() as outer:
        t = threading.Thread(target=other)
        t.start()
        assert inner_started.wait(5)
    outer_may_end.set()
    t.join()
    assert not outer.alone and not scopes["inner"].alone
