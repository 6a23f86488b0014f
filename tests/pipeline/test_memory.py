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


def test_release_memory_returns_a_finished_tasks_freed_heap_to_the_system():
    """Many small objects live on the C heap; freed, they stay resident until the heap is trimmed. A worker that ran
    a heavy task must not carry that into the next one (pipeline.execute.run_partition calls this after each)."""
    import ctypes.util

    import psutil

    from pipeline.memory import release_memory

    if not ctypes.util.find_library("c"):
        pytest.skip("no C library to trim")
    proc = psutil.Process()
    release_memory()
    before = proc.memory_info().rss
    blobs = [bytes(900) for _ in range(300_000)]  # ~300 MB in heap-sized pieces
    grown = proc.memory_info().rss - before
    del blobs
    release_memory()
    left = proc.memory_info().rss - before
    assert grown > 200 * 2**20
    assert left < 0.3 * grown
