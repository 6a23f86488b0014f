"""Module-level functions for the parallel_map tests (they must be importable in spawned processes)."""
from __future__ import annotations

import os

from pipeline.parallel import set_worker_state, worker_state


def remember(offset: float) -> None:
    set_worker_state(offset=offset)


def shifted_square(x: float) -> tuple[float, int]:
    return x * x + worker_state()["offset"], os.getpid()


BUILDS: list[int] = []  # in each process: how many times the cached value was built


def remember_cached(offset: float) -> None:
    """An initializer whose expensive part is kept across calls (``worker_cache``)."""
    from pipeline.parallel import worker_cache

    def build() -> float:
        BUILDS.append(1)
        return 10.0 * offset

    set_worker_state(offset=offset, big=worker_cache(("big", offset), build))


def shifted_square_with_builds(x: float) -> tuple[float, int, int, float]:
    state = worker_state()
    return x * x + state["offset"], os.getpid(), len(BUILDS), state["big"]


def state_keys(_x: float) -> tuple[str, ...]:
    return tuple(sorted(worker_state()))


def built_once_value(item: tuple[str, str]) -> tuple[list[float], int]:
    """``build_once`` of a slow value in ``folder``; every build appends this process's pid to ``log``."""
    import json
    import time

    from pipeline.parallel import build_once

    folder, log = item

    def build() -> list[float]:
        with open(log, "a") as fh:
            fh.write(f"{os.getpid()}\n")
        time.sleep(0.3)  # long enough for the other processes to ask while it is being built
        return [1.5, 2.5, 3.5]

    value = build_once(folder, "value.json", build, lambda v, fh: fh.write(json.dumps(v).encode()),
                       lambda path: json.loads(open(path).read()))  # a save/load pair of its own
    return value, os.getpid()


def threads_of_this_task(_x=None) -> int | None:
    from pipeline.parallel import task_threads

    return task_threads()
