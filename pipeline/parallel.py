"""Parallel map for the independent inner steps of a single-partition stage (many small registrations).

``parallel_map(fn, items, workers=N)`` returns ``[fn(x) for x in items]`` in order. Where it runs:
- ``workers <= 1`` or fewer than two items: in this process, in order (also inside a cluster task);
- inside a dask.distributed worker: as tasks on the same cluster (``worker_client``: the partition task secedes
  while they run, so a cluster of any size does the inner work);
- elsewhere: a process pool of ``workers`` (default: the usable cores) processes (``spawn``: no forked OpenMP state),
  one OpenMP/BLAS thread each, started with ``initializer(*initargs)`` (large shared inputs are sent once per
  process this way, not once per item);
- else (one usable core): in this process, in order.
``fn`` must be importable by name (a module-level function) and its items and results picklable and small.
Results are identical whichever way it ran (each item is computed alone). Progress: ``progress(done, total)``.
"""
from __future__ import annotations

import logging
import os
from typing import Any, Callable, Sequence

log = logging.getLogger(__name__)
_INIT_STATE: dict[str, Any] = {}


def worker_state() -> dict[str, Any]:
    """What ``initializer`` stored in this process (via ``set_worker_state``); empty in the calling process
    unless it set it itself."""
    return _INIT_STATE


def set_worker_state(**values: Any) -> None:
    _INIT_STATE.update(values)


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _in_distributed_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def parallel_map(fn: Callable[[Any], Any], items: Sequence[Any], *, workers: int | None = None,
                 initializer: Callable[..., None] | None = None, initargs: tuple = (),
                 progress: Callable[[int, int], None] | None = None) -> list[Any]:
    items = list(items)
    total = len(items)
    if total == 0:
        return []
    if (workers is not None and int(workers) <= 1) or total < 2:
        log.debug("parallel_map %s: %d items in this process", getattr(fn, "__name__", fn), total)
        if initializer is not None:
            initializer(*initargs)
        out = []
        for n, x in enumerate(items, 1):
            out.append(fn(x))
            if progress:
                progress(n, total)
        return out
    if _in_distributed_worker():
        log.debug("parallel_map %s: %d items as cluster tasks", getattr(fn, "__name__", fn), total)
        return _on_cluster(fn, items, initializer, initargs, progress)
    workers = default_workers() if workers is None else int(workers)
    if workers <= 1:
        return parallel_map(fn, items, workers=1, initializer=initializer, initargs=initargs, progress=progress)
    log.debug("parallel_map %s: %d items on %d processes", getattr(fn, "__name__", fn), total, min(workers, total))
    return _on_pool(fn, items, min(workers, total), initializer, initargs, progress)


def _on_pool(fn, items, workers, initializer, initargs, progress) -> list[Any]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from pipeline.execute import one_thread_per_process

    with one_thread_per_process():  # the spawned processes inherit the environment at start
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                 initializer=initializer, initargs=initargs) as pool:
            futures = {pool.submit(fn, x): n for n, x in enumerate(items)}
            out: list[Any] = [None] * len(items)
            for done, fut in enumerate(as_completed(futures), 1):
                out[futures[fut]] = fut.result()
                if progress:
                    progress(done, len(items))
    return out


def _call_with_init(fn, x, initializer, token, *initargs):
    """On a cluster worker: run ``initializer`` once per call of parallel_map (``token``) and process."""
    if initializer is not None and _INIT_STATE.get("_token") != token:
        initializer(*initargs)
        _INIT_STATE["_token"] = token
    return fn(x)


def _on_cluster(fn, items, initializer, initargs, progress) -> list[Any]:
    import uuid

    from distributed import as_completed, worker_client

    token = uuid.uuid4().hex
    with worker_client() as client:
        shared = client.scatter(list(initargs), broadcast=True) if initargs else []  # sent once per worker
        futures = [client.submit(_call_with_init, fn, x, initializer, token, *shared, pure=False) for x in items]
        done = 0
        for _ in as_completed(futures):
            done += 1
            if progress:
                progress(done, len(items))
        return client.gather(futures)
