"""Runs a whole plan as one dataflow: a stage's partition is submitted as soon as the partitions it reads are
committed, not after the whole upstream stage, so independent stages and the drives of a workflow overlap.

Which partition waits for what (the engine knows only partitionings, never what a stage computes):
- a per-drive or per-scan-chunk stage whose running producers are all per-drive or per-scan-chunk streams by
  drive: its partitions of drive ``d`` start when every producer's partitions of ``d`` are committed (their part
  markers written), and read exactly those partitions (``StoreInputReader`` ``provisional``); its chunk list of
  ``d`` is read the same way from its ``partition_source``;
- any other stage (single, per tile, or one with a ``plan`` function) waits for its producers' commits, and a
  stage that reads another's files by path (a drive ``${raw_drives}/...``) waits for that stage's commit;
- stages with no path between them run at the same time (corners beside the pose graph, markings beside the
  corner map).
Commit semantics are unchanged: a stage's manifest is written after its last partition, a partition's outputs
before its part marker, and committed stages are skipped by fingerprint.

Where tasks run: ``sync`` in order in this process; ``threads`` a thread pool; ``local``/``processes`` a spawn
process pool (one native thread per process) that lives for the whole run, with single-partition stages in a
thread of this process (their inner steps show in the progress display and their own ``parallel_map`` pools
start there); ``distributed``/``tcp://`` futures on the dask cluster (dask's local schedulers compute a static
graph, which cannot grow the partitions an upstream partition reveals; the cluster's futures can).
"""
from __future__ import annotations

import contextlib
import heapq
import logging
import shutil
import threading
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Any, Callable

from pipeline import storage
from pipeline.declare import Partitioning, PartitionKey
from pipeline.errors import StageError
from pipeline.execute import (
    Progress,
    Scheduler,
    _context,
    _task_spec,
    commit_stage,
    enumerate_partitions,
    run_partition,
    set_step_progress,
    task_key,
)
from pipeline.parallel import one_thread_per_process, process_pool
from pipeline.plan import Plan, StagePlan
from pipeline.store import data_root

log = logging.getLogger(__name__)
STREAMING = (Partitioning.PER_DRIVE, Partitioning.PER_SCAN_CHUNK)


def stage_ranks(plan: Plan) -> dict[str, int]:
    """Each stage's rank: how many stages the longest chain that reads its outputs holds (0 for a stage nothing in
    the plan reads). The local pool starts the tasks of a higher rank first (``TaskPool``): the odometry (read by
    the pose graph, then the map, markings and tiles) before the corners (read by the map only)."""
    made_by = {(ds, sp.fingerprint): name for name, sp in plan.stages.items() for ds in sp.outputs.values()}
    readers: dict[str, set[str]] = {name: set() for name in plan.stages}
    for name, sp in plan.stages.items():
        for key in list(sp.inputs.values()) + list(sp.path_inputs):
            if tuple(key) in made_by and made_by[tuple(key)] != name:
                readers[made_by[tuple(key)]].add(name)
    ranks: dict[str, int] = {}

    def rank(name: str, seen: frozenset = frozenset()) -> int:
        if name not in ranks:
            below = [rank(r, seen | {name}) for r in readers[name] if r not in seen]
            ranks[name] = 1 + max(below) if below else 0
        return ranks[name]

    for name in plan.stages:
        rank(name)
    return ranks


class TaskPool:
    """Submits engine tasks where the scheduler says; ``here=True`` keeps a task in this process.

    A local pool (``processes``, ``threads``) runs at most ``workers`` tasks at once and starts the waiting task of
    the highest ``priority`` first (then the earliest submitted): a stage the longer chain of stages waits on goes
    before one beside it (``stage_ranks``). On demo seed 1 the corners' partitions, queued between the odometry's,
    delayed the pose graph's start by the corners' CPU while the pose graph then left a core idle. A cluster gets the
    priority as dask's ``priority``."""

    def __init__(self, scheduler: Scheduler):
        self.kind = scheduler.kind
        self._client = scheduler._client
        self._pool = None
        self._here = None
        self._slots = 0
        self._waiting: list = []  # heap of (-priority, seq, fn, args, outer future)
        self._running = 0
        self._seq = 0
        self._lock = threading.Lock()  # _running: the executor's callback thread frees a slot
        workers = scheduler.workers
        if self.kind == "threads":
            self._pool = ThreadPoolExecutor(max_workers=workers)
        elif self.kind == "processes":
            self._pool = process_pool(workers)
            self._here = ThreadPoolExecutor(max_workers=2)
        if self._pool is not None:
            self._slots = max(1, int(workers))

    def submit(self, fn: Callable, *args: Any, key: str, here: bool = False, priority: int = 0):
        if self._client is not None:
            return self._client.submit(fn, *args, key=key, pure=False, priority=priority)
        if self._pool is None:  # sync: run now, in order
            fut: Future = Future()
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller through the future
                fut.set_exception(exc)
            return fut
        if here and self._here is not None:
            return self._here.submit(fn, *args)
        outer: Future = Future()
        with self._lock:
            self._seq += 1
            heapq.heappush(self._waiting, (-priority, self._seq, fn, args, outer))
        self._drain()
        return outer

    def _drain(self) -> None:
        """Start waiting tasks, highest priority first, while a worker is free."""
        while True:
            with self._lock:
                if not self._waiting or self._running >= self._slots:
                    return
                _, _, fn, args, outer = heapq.heappop(self._waiting)
                if not outer.set_running_or_notify_cancel():
                    continue
                self._running += 1
            inner = self._pool.submit(fn, *args)
            inner.add_done_callback(lambda f, o=outer: self._finished(f, o))

    def _finished(self, inner: Future, outer: Future) -> None:
        with self._lock:
            self._running -= 1
        if inner.cancelled():  # the pool shut down under it: the outer future already runs, so it cannot cancel
            outer.set_exception(CancelledError())
            return
        exc = inner.exception()
        if exc is not None:
            outer.set_exception(exc)
        else:
            outer.set_result(inner.result())

    def wait_any(self, futures: list) -> list:
        if self._client is not None:
            from distributed import wait as dwait

            return list(dwait(futures, return_when="FIRST_COMPLETED").done)
        done = list(wait(futures, return_when=FIRST_COMPLETED).done)
        self._drain()
        return done

    def close(self, cancel: bool) -> None:
        with self._lock:
            for *_, outer in self._waiting:  # never started
                outer.cancel()
            self._waiting.clear()
        if self._here is not None:  # a stopped or failed run does not wait for a single-partition stage's thread
            self._here.shutdown(wait=not cancel, cancel_futures=cancel)
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)


@dataclass
class _Stage:
    sp: StagePlan
    spec: dict[str, Any]
    producers: dict[str, str] = field(default_factory=dict)  # input arg -> producing stage running in this run
    after: set = field(default_factory=set)  # stages running in this run whose files it reads by path
    keys: dict[str, PartitionKey] = field(default_factory=dict)  # label -> key, submitted so far
    done: dict[str, dict] = field(default_factory=dict)  # label -> task result
    drives_expanded: set = field(default_factory=set)
    all_known: bool = False
    committed: bool = False
    t_submit: float | None = None
    outputs: dict | None = None

    @property
    def name(self) -> str:
        return self.sp.name

    def drive_done(self, drive: str) -> bool:
        """All of this stage's partitions of ``drive`` are committed (True once the stage itself is)."""
        if self.committed:
            return True
        if not (self.all_known or drive in self.drives_expanded):
            return False
        return all(lbl in self.done for lbl, k in self.keys.items() if k.drive == drive)


class Flow:
    def __init__(self, plan: Plan, scheduler: Scheduler, progress: Progress | None):
        self.plan, self.scheduler, self.progress = plan, scheduler, progress
        # a display (pipeline.progress.StageProgress) also shows a stage's inner steps and when it ends
        self._step = getattr(progress, "step", None)
        self._finish = getattr(progress, "finish", None)
        self.stages: dict[str, _Stage] = {}
        self.pending: dict[Any, tuple[str, str]] = {}  # future -> (stage, label)
        self.summary: dict[str, Any] = {}
        self.ranks = stage_ranks(plan)  # task priorities of the local pool (TaskPool)
        producers = {(ds, sp.fingerprint): sp.name for sp in plan.stages.values()
                     if sp.selected and not sp.committed for ds in sp.outputs.values()}
        for name, sp in plan.stages.items():
            if not sp.selected:
                continue
            if sp.committed:
                log.info("stage %s: skipped (fingerprint %s already committed)", name, sp.fp8)
                self.summary[name] = {"decision": "skipped", "fingerprint": sp.fingerprint[:16]}
                continue
            st = _Stage(sp, _task_spec(plan, sp))
            for arg, (ds, fp) in sp.inputs.items():
                if (ds, fp) in producers:
                    st.producers[arg] = producers[(ds, fp)]
                elif fp and data_root(plan.uri).manifest(ds, fp) is None \
                        and arg not in sp.decl.optional_inputs:
                    raise StageError(f"stage {name!r} input {arg!r}: dataset {ds!r} (fingerprint {fp[:8]}) is not "
                                     f"committed under {plan.uri}; hint: run its producer (drop --only)")
            st.after = {producers[key] for key in sp.path_inputs if key in producers}
            self.stages[name] = st

    # -- what can start ------------------------------------------------------------------------------------
    def _streams(self, st: _Stage) -> bool:
        if st.sp.decl.partition not in STREAMING or st.sp.decl.plan:
            return False
        return all(self.stages[p].sp.decl.partition in STREAMING and not self.stages[p].sp.decl.plan
                   for p in st.producers.values())

    def _drives(self, st: _Stage) -> list[str]:
        """Drives a streaming stage's partitions can belong to."""
        if st.sp.partitions is not None:
            return sorted({k.drive for k in st.sp.partitions if k.drive is not None})
        src = st.sp.decl.partition_source
        if src in st.producers:
            return self._drives(self.stages[st.producers[src]])
        return sorted(st.sp.drives)

    def _advance(self) -> None:
        for st in self.stages.values():
            if st.committed:
                continue
            if any(not self.stages[a].committed for a in st.after):
                continue
            running = [self.stages[p] for p in st.producers.values() if not self.stages[p].committed]
            if not st.all_known and not running:
                self._submit(st, enumerate_partitions(self.plan, st.sp), provisional=None)
                st.all_known = True
            elif not st.all_known and self._streams(st):
                for drive in self._drives(st):
                    if drive in st.drives_expanded or not all(u.drive_done(drive) for u in running):
                        continue
                    provisional = {arg: sorted(lbl for lbl, k in self.stages[p].keys.items() if k.drive == drive)
                                   for arg, p in st.producers.items() if not self.stages[p].committed}
                    self._submit(st, self._keys_of_drive(st, drive, provisional), provisional)
                    st.drives_expanded.add(drive)
            if st.all_known and len(st.done) == len(st.keys):
                self._commit(st)

    def _keys_of_drive(self, st: _Stage, drive: str, provisional: dict[str, list[str]]) -> list[PartitionKey]:
        if st.sp.partitions is not None:
            return [k for k in st.sp.partitions if k.drive == drive]
        src = st.sp.decl.partition_source
        ctx = _context(st.spec, PartitionKey(), storage.tmp_dir(self.plan.root, f"plan-{st.name}"), {}, provisional)
        return sorted({PartitionKey(drive=k.drive, chunk=k.chunk) for k in ctx.inputs.partitions(src)
                       if k.drive == drive})

    def _submit(self, st: _Stage, keys: list[PartitionKey], provisional: dict[str, list[str]] | None) -> None:
        if st.t_submit is None:
            st.t_submit = time.perf_counter()
            log.info("stage %s: running (fingerprint %s)", st.name, st.sp.fp8)
            if self.progress is not None and self.scheduler.kind != "distributed":
                set_step_progress(st.name, self._step_display(st.name))
        here = st.sp.decl.partition == Partitioning.SINGLE
        for pk in keys:
            if pk.label in st.keys:
                continue
            st.keys[pk.label] = pk
            fut = self.pool.submit(run_partition, st.spec, pk.as_dict(), provisional, key=task_key(st.sp, pk),
                                   here=here, priority=self.ranks.get(st.name, 0))
            self.pending[fut] = (st.name, pk.label)
        self._show(st)

    def _step_display(self, name: str) -> Callable[[str, int, int], None]:
        """Where stage ``name``'s inner steps (``StageContext.report_step``) go: its own row's step, or a row of
        their own for a plain progress callback."""
        if self._step is not None:
            return lambda step, d, t: self._step(name, step, d, t)
        return lambda step, d, t: self.progress(f"{name}: {step}", d, t)

    def _show(self, st: _Stage) -> None:
        if self.progress is not None:
            self.progress(st.name, len(st.done), len(st.keys))

    def _commit(self, st: _Stage) -> None:
        parts = [st.done[lbl] for lbl in sorted(st.done)]
        st.outputs = commit_stage(st.spec, parts)
        st.committed = st.sp.committed = st.sp.ran = True
        st.sp.reused_partitions = sum(bool(p.get("reused")) for p in parts)
        if st.sp.partitions is None:
            st.sp.partitions = sorted(st.keys.values())
        set_step_progress(st.name, None)
        if self._finish is not None:
            self._finish(st.name)
        starts = [p["t_start"] for p in parts if "t_start" in p]
        ends = [p["t_end"] for p in parts if "t_end" in p]
        self.summary[st.name] = {
            "decision": "ran", "fingerprint": st.sp.fingerprint[:16], "outputs": st.outputs,
            "wall_s": round(time.perf_counter() - (st.t_submit or time.perf_counter()), 3),
            "cpu_s": round(sum(p.get("cpu_s", 0.0) for p in parts), 3),
            "started_s": round(min(starts) - self.t0, 3) if starts else None,
            "ended_s": round(max(ends) - self.t0, 3) if ends else None,
            "partitions": len(parts), "partitions_reused": st.sp.reused_partitions,
            "peak_rss_mb": max((p["peak_rss_mb"] for p in parts if "peak_rss_mb" in p), default=None)}

    # -- the loop ------------------------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        self.t0 = time.time()
        with contextlib.ExitStack() as stack:
            stack.enter_context(one_thread_per_process(
                self.scheduler.workers if self.scheduler.kind == "processes" else None))
            ledger = storage.tmp_dir(self.plan.root, f"verified-{uuid.uuid4().hex[:12]}")
            stack.callback(shutil.rmtree, ledger, ignore_errors=True)
            for st in self.stages.values():  # a file is verified once per run (pipeline.store.verify_file)
                st.spec["verified_ledger"] = str(ledger)
            self.pool = TaskPool(self.scheduler)
            failed = True
            try:
                self._advance()
                while self.pending:
                    for fut in self.pool.wait_any(list(self.pending)):
                        name, label = self.pending.pop(fut)
                        st = self.stages[name]
                        st.done[label] = fut.result()  # a failed partition raises here; the run stops
                        self._show(st)
                    self._advance()
                stuck = [n for n, st in self.stages.items() if not st.committed]
                if stuck:
                    raise StageError(f"stages {stuck} could not start: their inputs never became available")
                failed = False
            finally:
                for name in self.stages:
                    set_step_progress(name, None)
                self.pool.close(cancel=failed)
        ordered = {n: self.summary[n] for n in self.plan.stages if n in self.summary}
        return ordered


def run_plan(plan: Plan, scheduler: Scheduler, progress: Progress | None = None) -> dict[str, Any]:
    """Run every selected, uncommitted stage of ``plan``; returns the run summary per stage (decision, outputs,
    wall and CPU seconds, when its first partition started and its last ended, seconds from the run's start)."""
    return Flow(plan, scheduler, progress).run()
