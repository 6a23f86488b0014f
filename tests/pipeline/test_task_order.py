"""The local pool's task order: a waiting task of a higher-ranked stage starts first (then the earliest submitted),
at most ``workers`` run at once, and a stage's rank is the length of the longest chain of stages reading it."""
from __future__ import annotations

import threading
import time

import pytest

from pipeline.execute import Scheduler
from pipeline.flow import TaskPool, stage_ranks
from tests.pipeline.test_engine import toy_stages, write_toy  # noqa: F401 - toy_stages: the toy registry


def _record(log: list, name: str, gate: threading.Event | None = None) -> str:
    log.append(("start", name))
    if gate is not None:
        assert gate.wait(10)
    time.sleep(0.01)
    log.append(("end", name))
    return name


def test_a_higher_priority_task_starts_before_earlier_lower_ones_and_workers_bound_the_running():
    pool = TaskPool(Scheduler("threads", workers=1))
    log: list = []
    gate = threading.Event()
    try:
        first = pool.submit(_record, log, "busy", gate, key="busy", priority=0)
        low = [pool.submit(_record, log, f"low{k}", key=f"low{k}", priority=1) for k in range(2)]
        high = pool.submit(_record, log, "high", key="high", priority=5)
        time.sleep(0.05)
        assert log == [("start", "busy")]  # one worker: nothing else started while it runs
        gate.set()
        pending = [first, high, *low]
        while pending:
            done = pool.wait_any(pending)
            pending = [f for f in pending if f not in done]
        assert [name for what, name in log if what == "start"] == ["busy", "high", "low0", "low1"]
        assert high.result() == "high"
    finally:
        gate.set()
        pool.close(cancel=False)


def _fail() -> None:
    raise RuntimeError("task failed")


def test_a_failed_task_reaches_its_future_and_frees_its_worker():
    pool = TaskPool(Scheduler("threads", workers=1))
    try:
        bad = pool.submit(_fail, key="bad")
        log: list = []
        good = pool.submit(_record, log, "after", key="after")
        pending = [bad, good]
        while pending:
            done = pool.wait_any(pending)
            pending = [f for f in pending if f not in done]
        with pytest.raises(RuntimeError, match="task failed"):
            bad.result()
        assert good.result() == "after"
    finally:
        pool.close(cancel=False)


def test_stage_ranks_follow_the_longest_chain_of_readers(tmp_path, toy_stages):  # noqa: F811 - the fixture
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow

    plan = make_plan(load_workflow(write_toy(tmp_path)), tmp_path / "root")
    assert stage_ranks(plan) == {"numbers": 2, "squares": 1, "total": 0}
