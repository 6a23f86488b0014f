"""A process's holds of a lock, shared by the two kinds of lock (``pipeline.locks``: flock files on a local root;
``pipeline.leases``: lease objects on an object store): holds nest (``reentrant_hold``), and a holder is named by
its command line (``this_command``)."""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator


@contextmanager
def reentrant_hold(
    held: dict,
    guard: threading.Lock,
    ident: object,
    exclusive: bool,
    label: str,
    acquire: Callable[[], Any],
    release: Callable[[Any], None],
) -> Iterator[None]:
    """A process's holds of one lock nest: a second hold of ``ident`` (``held[ident]``, an object with ``exclusive``
    and ``count``) inside the first shares it (a shared inside an exclusive one too; an exclusive inside a shared one
    is a RuntimeError); the first one acquires (``acquire()``) and, at its end, releases (``release(h)``). Used by the
    flock locks and by the lease locks (``pipeline.leases``)."""
    with guard:
        h = held.get(ident)
        if h is not None:
            if exclusive and not h.exclusive:
                raise RuntimeError(f"{label}: held shared by this process; it cannot be made exclusive")
            h.count += 1
    if h is not None:
        try:
            yield
        finally:
            with guard:
                h.count -= 1
        return
    h = acquire()
    with guard:
        held[ident] = h
    try:
        yield
    finally:
        with guard:
            held.pop(ident, None)
        release(h)


def this_command() -> str:
    """What this process is, for a holder record: its command line (``cornermap build --map city ...``)."""
    argv = [Path(sys.argv[0]).name] + sys.argv[1:] if sys.argv and sys.argv[0] else ["python"]
    return " ".join(argv)[:300]
