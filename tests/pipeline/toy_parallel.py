"""Module-level functions for the parallel_map tests (they must be importable in spawned processes)."""
from __future__ import annotations

import os

from pipeline.parallel import set_worker_state, worker_state


def remember(offset: float) -> None:
    set_worker_state(offset=offset)


def shifted_square(x: float) -> tuple[float, int]:
    return x * x + worker_state()["offset"], os.getpid()
