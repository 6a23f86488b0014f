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

Inside ``with shared_pool():`` the calls that would start a process pool share one instead: its processes start
(spawn, imports) once for the block, each call's initializer runs once per process and call (its state replaces the
previous call's), and what an initializer keeps with ``worker_cache`` stays for the later calls (a survey's index
across the pose graph's anchoring rounds). A block opened inside a cluster task keeps the cluster's workers instead:
their ``worker_cache`` values are kept under the block's token for its later calls, and dropped on every worker when
the block ends (a long-lived worker does not keep a stage's indices after the stage).

``build_once(folder, name, ...)`` shares a value between the processes instead of building it in each: the first
to need it builds it and writes it under ``folder`` (a stage's scratch directory), the others load it.

Every process pool of the engine comes from ``process_pool``: its processes end themselves when the process that
started them is gone (``ORPHAN_POLL_S``). Why: a run stopped by SIGKILL (a job scheduler's timeout, the OOM killer),
or by a SIGTERM that reaches only the engine's process, otherwise leaves its pool processes waiting in a queue read
that never ends, with their memory (a demo build killed in its pose graph: 4 processes, 2.35 GB). They ignore
SIGINT: a terminal's Ctrl-C reaches the whole process group, and the process that started them ends them
(``mapservice.cli``: exit 130, one line) where each would otherwise print a KeyboardInterrupt traceback. Their log
records go to the starting process, which shows them as its own (``_log_relay``).
"""
from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
from contextvars import ContextVar
from typing import Any, Callable, Iterator, Sequence

log = logging.getLogger(__name__)
_INIT_STATE: dict[str, Any] = {}
_CACHE: dict[Any, Any] = {}  # this process's worker_cache, by (block, key)
_SHARED: list[dict[str, Any]] = []  # the open shared_pool blocks, innermost last
_BLOCK: ContextVar[str | None] = ContextVar("cornermap_parallel_block", default=None)  # the running item's block


ORPHAN_POLL_S = 1.0  # how often a pool process checks that the process that started it is still there
ORPHAN_EXIT_CODE = 129  # a pool process that ended itself because that process was gone (128 + SIGHUP)


def process_pool(workers: int, initializer: Callable[..., None] | None = None, initargs: tuple = ()):
    """A spawn-context ``ProcessPoolExecutor`` of ``workers`` processes (no forked OpenMP state), each started with
    ``initializer(*initargs)`` after a watch thread that ends the process (``os._exit``, ``ORPHAN_EXIT_CODE``) once
    the process that started it is gone, with SIGINT ignored and its log records relayed here (``_log_relay``). A
    task cut off that way leaves nothing visible: outputs are written to a temporary name and renamed
    (``pipeline.store``)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    logs, level = _log_relay(), logging.getLogger().getEffectiveLevel()
    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_start_pool_process,
                               initargs=(os.getpid(), logs, level, initializer, initargs))


def _start_pool_process(parent_pid: int, logs, level: int, initializer: Callable[..., None] | None,
                        initargs: tuple) -> None:
    import logging.handlers
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=exit_when_orphaned, args=(parent_pid,), name="cornermap-orphan-watch", daemon=True).start()
    root = logging.getLogger()  # log records go to the starting process, which shows them as its own
    logs.cancel_join_thread()  # exiting never waits on the queue (a sibling killed while writing would hold its lock)
    root.handlers = [logging.handlers.QueueHandler(logs)]
    root.setLevel(level)
    if initializer is not None:
        initializer(*initargs)


_RELAY: list = []  # this process's (queue, thread) relaying its pool processes' log records


def _log_relay():
    """The queue this process's pool processes put their log records on (started once per process): a thread here
    hands each to this process's logger of the same name, so a pool process's warning is shown as this process's
    (its format, its level, above a live progress display) rather than written to the terminal by the child."""
    if not _RELAY:
        import multiprocessing as mp

        queue = mp.get_context("spawn").Queue()

        def relay() -> None:
            while True:
                try:
                    record = queue.get()
                except (EOFError, OSError):  # the process is ending
                    return
                logging.getLogger(record.name).handle(record)

        thread = threading.Thread(target=relay, name="cornermap-pool-logs", daemon=True)
        thread.start()
        _RELAY.append((queue, thread))
    return _RELAY[0][0]


def exit_when_orphaned(parent_pid: int, poll_s: float = ORPHAN_POLL_S) -> None:
    """Return never: end this process as soon as its parent is no longer ``parent_pid`` (the parent died and the
    process was handed to init or a subreaper)."""
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(ORPHAN_EXIT_CODE)


EXIT_WITH_PARENT_VARIABLE = "CORNERMAP_EXIT_WITH_PARENT"  # set by mapservice.child.run_cornermap for its child


def exit_with_parent_from_env(variable: str = EXIT_WITH_PARENT_VARIABLE) -> None:
    """When ``variable`` names this process's parent pid, watch it like a pool process does (``exit_when_orphaned``,
    in a daemon thread): the command a parent started (``mapservice.child.run_cornermap``: the rebuild's drive
    checks, the regression gate's evaluations)
    ends within ``ORPHAN_POLL_S`` once that parent is gone, and its own pool processes follow it."""
    value = os.environ.pop(variable, "")
    if value.isdigit():
        threading.Thread(target=exit_when_orphaned, args=(int(value),), name="cornermap-orphan-watch",
                         daemon=True).start()


def worker_state() -> dict[str, Any]:
    """What ``initializer`` stored in this process (via ``set_worker_state``); empty in the calling process
    unless it set it itself."""
    return _INIT_STATE


def set_worker_state(**values: Any) -> None:
    _INIT_STATE.update(values)


def worker_cache(key: Any, build: Callable[[], Any]) -> Any:
    """``build()``, kept under ``key`` (hashable, the same in every process: not an ``id``) for the later calls of a
    ``shared_pool`` block, while an item of one of its calls runs: in the block's processes, which end with it, or on
    a cluster worker, until the block ends (``_forget_block``). Elsewhere (this process, a pool of one call, a cluster
    task outside a block) it is built every time and nothing is kept."""
    block = _BLOCK.get()
    if block is None:
        return build()
    if (block, key) not in _CACHE:
        _CACHE[(block, key)] = build()
    return _CACHE[(block, key)]


def _save_array(value: Any, fh) -> None:
    import numpy as np

    np.save(fh, value, allow_pickle=False)


def _load_array(path: str) -> Any:
    import numpy as np

    return np.load(path, allow_pickle=False)


def build_once(folder: "os.PathLike | str | None", name: str, build: Callable[[], Any],
               save: Callable[[Any, Any], None] = _save_array, load: Callable[[str], Any] = _load_array) -> Any:
    """``build()`` computed once among the processes that share ``folder`` (a stage's scratch directory: a pool's
    processes, or the workers of a cluster that see the stage's root): the first to need ``name`` holds its lock
    (``fcntl.flock``, released by the kernel if the holder dies), builds it and writes it with ``save(value, binary
    file)`` to a temporary file renamed into place; the others wait for the lock and ``load(path)`` it (default: a
    numpy array as ``.npy``, no pickle). The value
    must be a pure function of what ``name`` says: whoever builds it, every process gets the same value. A file
    that cannot be loaded is built again here (a warning); without advisory locks (a file system that refuses
    them) processes may build it at once, each renaming its own complete file into place; ``folder`` None builds in
    this process, nothing kept."""
    import uuid
    from pathlib import Path

    if folder is None:
        return build()
    folder = Path(folder)
    path = folder / name

    def loaded() -> tuple[bool, Any]:
        if not path.exists():
            return False, None
        try:
            return True, load(str(path))
        except (OSError, ValueError, EOFError) as exc:
            log.warning("build_once: cannot load %s (%s); building it again in this process", path, exc)
            return True, build()

    found, value = loaded()
    if found:
        return value
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f".{name}.lock", "a+b") as lock:
        try:
            import fcntl

            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        except (ImportError, OSError) as exc:  # no advisory locks (platform, file system): the processes may each
            log.debug("build_once: no lock on %s (%s)", folder, exc)  # build it, with the same result
        found, value = loaded()
        if found:
            return value
        value = build()
        tmp = folder / f".{name}.tmp-{uuid.uuid4().hex[:8]}"
        try:
            with open(tmp, "wb") as fh:
                save(value, fh)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return value  # the lock is released when its file closes


def _forget_block(block: str) -> int:
    """On a cluster worker (``Client.run``): drop the ``worker_cache`` values of a block that ended."""
    stale = [k for k in _CACHE if k[0] == block]
    for k in stale:
        del _CACHE[k]
    if stale:
        from pipeline.memory import release_memory

        release_memory()
    return len(stale)


@contextlib.contextmanager
def shared_pool(workers: int | None = None) -> Iterator[None]:
    """The ``parallel_map`` calls of this thread's block that would each start a process pool share one of
    ``workers`` processes (default: the usable cores), started at the first such call and shut at the end."""
    import tempfile
    import uuid

    holder: dict[str, Any] = {"pool": None, "workers": workers or default_workers(), "dir": None,
                              "block": uuid.uuid4().hex, "cluster": False}
    _SHARED.append(holder)
    try:
        with tempfile.TemporaryDirectory(prefix="cornermap-pool-") as folder:
            holder["dir"] = folder
            try:
                yield
            finally:
                if holder["pool"] is not None:
                    holder["pool"].shutdown(wait=True, cancel_futures=True)
                if holder["cluster"]:
                    _forget_on_cluster(holder["block"])
    finally:
        _SHARED.remove(holder)


def _forget_on_cluster(block: str) -> None:
    from distributed import worker_client

    try:
        with worker_client() as client:
            client.run(_forget_block, block)
    except Exception as exc:  # noqa: BLE001 - a worker gone; its cache went with it
        log.warning("parallel_map: could not drop a block's cached values on every worker (%s)", exc)


# Native thread pools of the libraries a task may call (OpenMP: open3d; BLAS). A pool of one process per core
# with each process also starting a thread per core oversubscribes the machine; dask.distributed's nanny sets the
# same variables for its workers (``distributed.nanny.pre-spawn-environ``).
THREAD_POOL_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


# The cores a pool's process may use (``pipeline.parallel.task_threads``), for the native pools that ignore the
# variables above (Open3D's oneTBB); set by ``one_thread_per_process`` for the processes it starts.
TASK_THREADS_VARIABLE = "CORNERMAP_TASK_THREADS"


@contextlib.contextmanager
def one_thread_per_process(processes: int | None = None):
    """Within the block, newly spawned processes start their native thread pools with one thread, unless the
    user set the variable; the parent's environment is restored afterwards. ``processes``: how many the block's
    pool starts; each is then told its share of the usable cores (at least 1) in ``TASK_THREADS_VARIABLE``."""
    names = THREAD_POOL_VARIABLES + ((TASK_THREADS_VARIABLE,) if processes else ())
    saved = {v: os.environ.get(v) for v in names}
    for v, value in saved.items():
        if value is None:
            os.environ[v] = "1"
    if processes:
        os.environ[TASK_THREADS_VARIABLE] = str(max(1, default_workers() // max(1, int(processes))))
    try:
        yield
    finally:
        for v, value in saved.items():
            if value is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = value


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def task_threads() -> int | None:
    """The cores the current task may use: the threads of the dask worker running it (its ``nthreads``: the cores
    the cluster counts it for); in a process of a local pool (the engine's, ``parallel_map``'s), its share of the
    usable cores (``one_thread_per_process``); None elsewhere (this process decides). A library
    whose thread pool ignores ``OMP_NUM_THREADS`` is bounded to this by its caller (Open3D's oneTBB:
    ``stages.common.registration``). Measured on demo seed 1's odometry, 2 pool processes on 2 cores: 62.5-63.4 s
    with each process's oneTBB on both cores, 59.9-60.7 s bounded to one."""
    cluster = _cluster_task_threads()
    if cluster is not None:
        return cluster
    share = os.environ.get(TASK_THREADS_VARIABLE, "")
    return int(share) if share.isdigit() and int(share) > 0 else None


def _cluster_task_threads() -> int | None:
    """The ``nthreads`` of the dask worker running the current task, or None outside a cluster task."""
    if "distributed" not in sys.modules:  # not a dask worker process; do not import dask for the answer
        return None
    try:
        from distributed import get_worker

        return int(get_worker().state.nthreads)
    except (ValueError, AttributeError):  # no task of a worker in this context
        return None


def _in_distributed_worker() -> bool:
    return _cluster_task_threads() is not None


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
    if _SHARED:
        log.debug("parallel_map %s: %d items on the shared pool", getattr(fn, "__name__", fn), total)
        return _on_shared_pool(_SHARED[-1], fn, items, initializer, initargs, progress)
    workers = default_workers() if workers is None else int(workers)
    if workers <= 1:
        return parallel_map(fn, items, workers=1, initializer=initializer, initargs=initargs, progress=progress)
    log.debug("parallel_map %s: %d items on %d processes", getattr(fn, "__name__", fn), total, min(workers, total))
    return _on_pool(fn, items, min(workers, total), initializer, initargs, progress)


def _on_pool(fn, items, workers, initializer, initargs, progress) -> list[Any]:
    with one_thread_per_process(workers):  # the spawned processes inherit the environment at start
        with process_pool(workers, initializer, initargs) as pool:
            return _gathered({pool.submit(fn, x): n for n, x in enumerate(items)}, progress)


def _gathered(futures: dict, progress) -> list[Any]:
    """The results of ``{future: item index}`` in item order, with ``progress(done, total)`` as they finish."""
    from concurrent.futures import as_completed

    out: list[Any] = [None] * len(futures)
    for done, fut in enumerate(as_completed(futures), 1):
        out[futures[fut]] = fut.result()
        if progress:
            progress(done, len(futures))
    return out


def _call_with_init(fn, x, initializer, token, block, *initargs):
    """On a cluster worker: run ``initializer`` once per call of parallel_map (``token``) and process, with the
    ``worker_cache`` of ``block`` (a ``shared_pool`` block's token, or None)."""
    from pipeline.memory import relax_malloc_trim

    relax_malloc_trim()  # once per process: dask's worker environment (pipeline.memory)
    reset = _BLOCK.set(block)
    try:
        if initializer is not None and _INIT_STATE.get("_token") != token:
            initializer(*initargs)
            _INIT_STATE["_token"] = token
        return fn(x)
    finally:
        _BLOCK.reset(reset)


def _on_cluster(fn, items, initializer, initargs, progress) -> list[Any]:
    import uuid

    from distributed import as_completed, worker_client

    token = uuid.uuid4().hex
    block = None
    if _SHARED:
        _SHARED[-1]["cluster"] = True
        block = _SHARED[-1]["block"]
    with worker_client() as client:
        # sent once per worker; keys of their own (a content-hashed key of an earlier call's equal initargs can be
        # released under this call's tasks: 'lost dependencies')
        shared = client.scatter(list(initargs), broadcast=True, hash=False) if initargs else []
        futures = [client.submit(_call_with_init, fn, x, initializer, token, block, *shared, pure=False)
                   for x in items]
        done = 0
        for _ in as_completed(futures):
            done += 1
            if progress:
                progress(done, len(items))
        return client.gather(futures)


def _pooled_call(fn, x, token: str, block: str, init_path: str | None):
    """In a shared pool's process: this call's initializer (read from its file) once per process and call, then
    ``fn(x)``, both with the ``worker_cache`` of ``block``. The previous call's state is dropped first; the cache is
    kept."""
    from pipeline.memory import relax_malloc_trim

    relax_malloc_trim()
    reset = _BLOCK.set(block)
    try:
        if _INIT_STATE.get("_token") != token:
            _INIT_STATE.clear()
            if init_path is not None:
                import pickle

                with open(init_path, "rb") as f:
                    initializer, initargs = pickle.load(f)
                initializer(*initargs)
            _INIT_STATE["_token"] = token
        return fn(x)
    finally:
        _BLOCK.reset(reset)


def _on_shared_pool(holder: dict[str, Any], fn, items, initializer, initargs, progress) -> list[Any]:
    import pickle
    import uuid
    from pathlib import Path

    token = uuid.uuid4().hex
    init_path = None
    if initializer is not None:  # sent once as a file, not with every item
        init_path = Path(holder["dir"]) / f"{token}.pickle"
        with open(init_path, "wb") as f:
            pickle.dump((initializer, initargs), f, protocol=pickle.HIGHEST_PROTOCOL)
    try:
        with one_thread_per_process(holder["workers"]):  # processes start at a submit, inherit the environment then
            if holder["pool"] is None:
                holder["pool"] = process_pool(holder["workers"])
            futures = {holder["pool"].submit(_pooled_call, fn, x, token, holder["block"],
                                             None if init_path is None else str(init_path)): n
                       for n, x in enumerate(items)}
        return _gathered(futures, progress)
    finally:
        if init_path is not None:
            init_path.unlink(missing_ok=True)
