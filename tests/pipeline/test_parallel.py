"""parallel_map: the same results in order whichever way it runs (in process, process pool, cluster tasks),
with the initializer's state in every worker and progress reported to the end."""
from __future__ import annotations

import os

import pytest

from pipeline.parallel import parallel_map
from tests.pipeline.toy_parallel import remember, shifted_square

ITEMS = [float(i) for i in range(12)]
EXPECTED = [x * x + 0.5 for x in ITEMS]


@pytest.mark.parametrize("workers", [1, 2])
def test_results_in_order_with_initializer_state(workers):
    seen = []
    out = parallel_map(shifted_square, ITEMS, workers=workers, initializer=remember, initargs=(0.5,),
                       progress=lambda done, total: seen.append((done, total)))
    assert [v for v, _ in out] == EXPECTED
    pids = {pid for _, pid in out}
    assert (pids == {os.getpid()}) if workers == 1 else (os.getpid() not in pids)
    assert seen[-1] == (12, 12) and len(seen) == 12


def test_inside_a_cluster_task_the_items_run_as_cluster_tasks():
    distributed = pytest.importorskip("distributed")

    def outer(_):
        return parallel_map(shifted_square, ITEMS, initializer=remember, initargs=(0.5,))

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        out = client.submit(outer, 0).result()
    assert [v for v, _ in out] == EXPECTED


def test_empty_and_single_item_run_in_process():
    assert parallel_map(shifted_square, [], workers=4) == []
    assert parallel_map(shifted_square, [2.0], workers=4, initializer=remember, initargs=(1.0,))[0][0] == 5.0


def test_a_serial_request_inside_a_cluster_task_stays_in_process(monkeypatch):
    """workers=1 means this process even inside a dask.distributed worker (the cluster branch is not taken)."""
    import pipeline.parallel as par

    def no_cluster(*_a, **_k):
        raise AssertionError("workers=1 went to the cluster")

    monkeypatch.setattr(par, "_in_distributed_worker", lambda: True)
    monkeypatch.setattr(par, "_on_cluster", no_cluster)
    out = parallel_map(shifted_square, ITEMS, workers=1, initializer=remember, initargs=(0.5,))
    assert [v for v, _ in out] == EXPECTED and {pid for _, pid in out} == {os.getpid()}


def test_calls_in_a_shared_pool_reuse_its_processes_and_the_worker_cache():
    """Three calls in one shared_pool block: the same (spawned) processes serve all of them, each call's initializer
    state is its own, and a worker_cache value is built once per process, not once per call."""
    from pipeline.parallel import shared_pool
    from tests.pipeline.toy_parallel import remember_cached, shifted_square_with_builds, state_keys

    with shared_pool(workers=2):
        first = parallel_map(shifted_square_with_builds, ITEMS, initializer=remember_cached, initargs=(0.5,))
        second = parallel_map(shifted_square_with_builds, ITEMS, initializer=remember_cached, initargs=(0.5,))
        other = parallel_map(shifted_square, ITEMS, initializer=remember, initargs=(2.0,))
        keys = parallel_map(state_keys, ITEMS)  # no initializer: the previous call's state is gone
    assert [v for v, *_ in first] == EXPECTED and [v for v, *_ in second] == EXPECTED
    assert [v for v, _ in other] == [x * x + 2.0 for x in ITEMS]
    # the pool's two processes served every call: a pool per call would have started at least one new process for
    # each of the three (a process may take no item of a call, so a later call can be the first to use the second)
    pids = {p for _, p, *_ in first} | {p for _, p, *_ in second} | {p for _, p in other}
    assert os.getpid() not in pids and len(pids) <= 2
    assert all(builds == 1 for *_, builds, _ in second)  # built at the first call, kept for the second
    assert all(big == 5.0 for *_, big in first + second)
    assert all(k == ("_token",) for k in keys)


def test_a_failing_item_in_a_shared_pool_raises_and_the_block_still_closes():
    from pipeline.parallel import shared_pool
    from tests.pipeline.toy_parallel import shifted_square as needs_state

    with pytest.raises(KeyError):
        with shared_pool(workers=2):
            parallel_map(needs_state, ITEMS)  # no initializer: worker_state() has no "offset"
    assert parallel_map(shifted_square, ITEMS, workers=1, initializer=remember, initargs=(0.5,))[0][0] == 0.5


def test_outside_a_shared_pool_the_worker_cache_keeps_nothing():
    """In this process (or a long-lived cluster worker) a cached value would outlive the stage: it is built anew."""
    from pipeline.parallel import worker_cache

    built = []
    for _ in range(2):
        worker_cache("k", lambda: built.append(1))
    assert len(built) == 2


def test_a_shared_pool_block_in_a_cluster_task_keeps_the_worker_cache_until_it_ends():
    """Inside a cluster task, the calls of a shared_pool block run as cluster tasks; a worker_cache value built in the
    first call is used by the second (no new builds), and every worker drops it when the block ends."""
    distributed = pytest.importorskip("distributed")
    import pipeline.parallel as par
    from tests.pipeline import toy_parallel

    def outer(_):
        from pipeline.parallel import shared_pool
        from tests.pipeline.toy_parallel import BUILDS, remember_cached, shifted_square_with_builds

        with shared_pool():
            first = parallel_map(shifted_square_with_builds, ITEMS, initializer=remember_cached, initargs=(0.5,))
            built = len(BUILDS)
            second = parallel_map(shifted_square_with_builds, ITEMS, initializer=remember_cached, initargs=(0.5,))
            kept = sum(1 for k in par._CACHE if k[0] is not None)
        return first, second, built, kept

    toy_parallel.BUILDS.clear()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        first, second, built, kept = client.submit(outer, 0).result()
    assert [v for v, *_ in first] == EXPECTED and [v for v, *_ in second] == EXPECTED
    assert 1 <= built <= 2 and all(b == built for _, _, b, _ in second)  # the second call built nothing
    assert kept >= 1  # held while the block was open
    assert not [k for k in par._CACHE if k[0] is not None]  # and dropped when it ended


def test_task_threads_is_the_workers_thread_count_inside_a_cluster_task_and_none_elsewhere():
    distributed = pytest.importorskip("distributed")
    from pipeline.parallel import task_threads
    from tests.pipeline.toy_parallel import threads_of_this_task

    assert task_threads() is None
    with distributed.LocalCluster(n_workers=1, threads_per_worker=3, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        assert client.submit(threads_of_this_task, 0).result() == 3
        assert task_threads() is None  # the client's own thread is no task


def test_task_threads_in_a_local_pool_is_each_process_share_of_the_cores(monkeypatch):
    """A pool's processes are told their share of the usable cores (Open3D's oneTBB ignores OMP_NUM_THREADS and
    is bounded to it); the calling process is not, and its environment is restored after the pool."""
    from pipeline.parallel import TASK_THREADS_VARIABLE, default_workers, shared_pool, task_threads
    from tests.pipeline.toy_parallel import threads_of_this_task

    monkeypatch.delenv(TASK_THREADS_VARIABLE, raising=False)
    assert task_threads() is None
    assert parallel_map(threads_of_this_task, [0, 1, 2], workers=2) == [max(1, default_workers() // 2)] * 3
    assert parallel_map(threads_of_this_task, [0, 1], workers=1) == [None, None]  # in this process
    with shared_pool(workers=3):
        assert parallel_map(threads_of_this_task, [0, 1, 2]) == [max(1, default_workers() // 3)] * 3
    assert TASK_THREADS_VARIABLE not in os.environ and task_threads() is None


def test_one_thread_per_process_sets_the_share_for_the_block_and_restores_a_callers_value(monkeypatch):
    from pipeline.parallel import TASK_THREADS_VARIABLE, default_workers, one_thread_per_process

    monkeypatch.setenv(TASK_THREADS_VARIABLE, "7")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with one_thread_per_process(processes=64):
        assert os.environ[TASK_THREADS_VARIABLE] == "1" and os.environ["OMP_NUM_THREADS"] == "1"
    assert os.environ[TASK_THREADS_VARIABLE] == "7" and "OMP_NUM_THREADS" not in os.environ
    with one_thread_per_process(processes=1):
        assert os.environ[TASK_THREADS_VARIABLE] == str(default_workers())
    with one_thread_per_process():  # no pool size: the variable as the caller left it
        assert os.environ[TASK_THREADS_VARIABLE] == "7"
