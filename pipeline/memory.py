"""Peak resident memory of a task, and the workflow's memory budget check.

Each task samples its process's resident set size (RSS) in a background thread while it runs: that is the
memory a worker process needs for the partition (its libraries included), which is what a cluster's worker
memory limit is compared against. A single-partition stage run in a thread of the calling process shares that
process with others: its figure is the process's, an upper bound of the stage's own.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import threading
from typing import Any, Iterator

MB = 2**20


class PeakRss:
    """Context manager: ``peak_mb`` is the largest RSS of this process seen while the block ran (sampled every
    ``interval_s``, and once at entry and exit, so a task shorter than the interval still gets a figure)."""

    def __init__(self, interval_s: float = 0.1):
        self.interval_s = interval_s
        self.peak_mb = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        try:
            self.peak_mb = max(self.peak_mb, self._proc.memory_info().rss / MB)
        except Exception:  # noqa: BLE001 - a process being torn down; the figure keeps its last value
            pass

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def __enter__(self) -> "PeakRss":
        import psutil

        self._proc = psutil.Process()
        self._sample()
        self._thread = threading.Thread(target=self._loop, name="peak-rss", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()


def release_memory(trim_above_mb: float | None = None) -> None:
    """Hand the memory a finished task freed back to the system, so that the next task of the same worker process
    starts from the libraries' footprint, not from the previous task's high-water mark: a cycle collection, Arrow's
    pool's unused pages, and glibc's free heap top and arenas (``malloc_trim``; skipped where there is no glibc).
    Measured on demo seed 1: six corners partitions run one after another in one process kept 300-630 MB resident
    between tasks, 190-270 MB with this call after each.

    ``trim_above_mb``: trim glibc's heap only while the process holds more than this (None: always). A trimmed heap
    costs the next task its page faults: a demo build that never trimmed took 129.5 s instead of 137.8 s (odometry
    87.8 CPU s instead of 102.7) and its largest process grew 965 -> 1295 MB."""
    import gc

    gc.collect()
    try:
        import pyarrow as pa

        pa.default_memory_pool().release_unused()
    except Exception:  # noqa: BLE001 - a pool without the call; nothing to release
        pass
    malloc_trim = _glibc("malloc_trim")
    if malloc_trim is not None and (trim_above_mb is None or _rss_mb() > trim_above_mb):
        malloc_trim(0)


TRIM_SHARE_OF_BUDGET = 0.75


def trim_threshold_mb(memory_budget_mb: float | None) -> float | None:
    """The resident size below which a task process keeps its freed heap for the next task (``release_memory``):
    ``TRIM_SHARE_OF_BUDGET`` of the workflow's memory budget (1152 MB of the default 1536), None (always trim) without a
    budget. Measured on demo seed 1: build 137.8 -> 125.2 s, system CPU 32 -> 22 s, largest process 965 -> 1058 MB."""
    return TRIM_SHARE_OF_BUDGET * memory_budget_mb if memory_budget_mb else None


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / MB


_ACTIVE_TASKS = [0]  # tasks running in this process (a thread scheduler runs several at once)
_STARTED_TASKS = [0]  # tasks started in this process so far
_ACTIVE_LOCK = threading.Lock()


@dataclasses.dataclass
class TaskScope:
    alone: bool = False  # set at the task's end: no other task of this process ran at any moment of it


@contextlib.contextmanager
def task_scope(trim_above_mb: float | None = None) -> Iterator[TaskScope]:
    """Around one task: at its end, its garbage is collected and returned (``release_memory``), and when no other
    task of this process is running, every object still tracked by Python's cycle collector (the modules, the
    libraries' state, the caches kept between tasks) moves to the collector's permanent generation (``gc.freeze``),
    so that the next tasks' collections scan only the objects those tasks make. Frozen objects are still freed when
    their last reference goes; only a reference cycle among them would stay. Measured with py-spy on a demo build:
    the pool processes' ``gc.collect`` after each task took ~8 CPU s of the build (~80 ms a task). The scope says at
    the end whether the task ran alone in its process (``TaskScope.alone``: its CPU is then the process's)."""
    import gc

    scope = TaskScope()
    with _ACTIVE_LOCK:
        _ACTIVE_TASKS[0] += 1
        _STARTED_TASKS[0] += 1
        first, started = _ACTIVE_TASKS[0] == 1, _STARTED_TASKS[0]
    try:
        yield scope
    finally:
        release_memory(trim_above_mb)
        with _ACTIVE_LOCK:
            scope.alone = first and _STARTED_TASKS[0] == started
            _ACTIVE_TASKS[0] -= 1
            if _ACTIVE_TASKS[0] == 0:  # another task's live objects would otherwise never be scanned again
                gc.freeze()


@functools.cache
def _glibc(name: str):
    """The C library's function ``name`` (glibc's ``malloc_trim``, ``mallopt``), or None where there is none."""
    import ctypes
    import ctypes.util

    libc = ctypes.util.find_library("c")
    if not libc:
        return None
    try:
        return getattr(ctypes.CDLL(libc), name)
    except (OSError, AttributeError):  # not glibc
        return None


# glibc's mallopt parameters (malloc.h) and the values a task process runs with when its environment asks for an
# aggressive trim (``relax_malloc_trim``)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
TASK_MMAP_THRESHOLD_BYTES = 8 * MB
TASK_TRIM_THRESHOLD_BYTES = 16 * MB


def malloc_needs_relaxing(environ) -> bool:
    """Whether a process started with ``environ`` runs glibc's allocator with a trim threshold that makes every
    large temporary array a fresh ``mmap``: ``MALLOC_TRIM_THRESHOLD_`` set below ``TASK_TRIM_THRESHOLD_BYTES`` and
    ``MALLOC_MMAP_THRESHOLD_`` not set. dask's nanny starts every worker so (``distributed.nanny.pre-spawn-environ``:
    65536 bytes), and setting any threshold turns off glibc's dynamic mmap threshold, which would otherwise rise to
    the size of the arrays a task frees."""
    trim = environ.get("MALLOC_TRIM_THRESHOLD_")
    if trim is None or "MALLOC_MMAP_THRESHOLD_" in environ:
        return False
    try:
        return int(trim) < TASK_TRIM_THRESHOLD_BYTES
    except ValueError:
        return False


@functools.cache  # once per process
def relax_malloc_trim() -> bool:
    """Once per process, where ``malloc_needs_relaxing`` says so (a dask worker): let glibc keep freed blocks up to
    ``TASK_MMAP_THRESHOLD_BYTES`` in its heap and trim the heap top only above ``TASK_TRIM_THRESHOLD_BYTES``
    (``mallopt``). Memory still goes back to the system after every task (``release_memory``). Returns whether the
    settings were changed. Measured on this project's 2-core machine, 300 demo scans through the odometry in one
    process: 4.98 s with glibc's defaults, 7.98 s with dask's ``MALLOC_TRIM_THRESHOLD_=65536``, 4.72 s with it and
    these settings; the whole demo build on a 2-worker LocalCluster spent 170 CPU s in the odometry against 117 on
    the local pool. A user who sets ``MALLOC_MMAP_THRESHOLD_`` keeps their settings."""
    import os

    mallopt = _glibc("mallopt") if malloc_needs_relaxing(os.environ) else None
    return bool(mallopt is not None and mallopt(_M_MMAP_THRESHOLD, TASK_MMAP_THRESHOLD_BYTES)
                and mallopt(_M_TRIM_THRESHOLD, TASK_TRIM_THRESHOLD_BYTES))


def over_budget(summary: dict[str, dict[str, Any]], budget_mb: float | None) -> list[str]:
    """One line per stage whose task peak RSS exceeded ``budget_mb`` (None: no budget, no lines)."""
    if not budget_mb:
        return []
    lines = []
    for stage, s in summary.items():
        peak = s.get("peak_rss_mb")
        if peak is not None and peak > budget_mb:
            lines.append(f"memory: stage {stage!r} peaked at {peak:.0f} MB per task, over the workflow's "
                         f"memory_budget_mb {budget_mb:.0f}")
    return lines
