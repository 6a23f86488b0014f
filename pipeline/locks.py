"""Who may write an output root or a map at the same time: the locks every writer takes (knows nothing about LiDAR).

Two scopes, each one lock with a mode (``docs/maintenance.md``, "Locks"):

==========  =======================================  ====================================================
lock        shared by                                exclusive for
==========  =======================================  ====================================================
``root``    every run that writes datasets (``run``,  ``gc --apply`` (it deletes what runs read)
            ``build``, ``rebuild``)
``map/N``   -                                        whatever publishes a version of map N or moves its
                                                     LATEST: a run whose workflow publishes N (``run``,
                                                     ``build``), ``rebuild`` of N, ``tiles rollback``
==========  =======================================  ====================================================

Every lock is taken without waiting: a writer that cannot have it stops before writing anything and raises
``RunLockedError`` (exit 75, EX_TEMPFAIL) naming a holder. Readers (``tiles ls|verify|export``, ``maps show``,
``evaluate`` of a published version, the loader) take none: published versions are immutable and LATEST is replaced
atomically, so a reader never needs to wait. A process holding a lock may take it again (nested ``hold``: a rebuild
runs its build in the same process); a shared hold cannot be made exclusive (a ``RuntimeError``: a bug).

The one interface is ``locks_for(root).hold(key, exclusive=..., what=...)``: a context manager. The local backend
(``FileLocks``) is ``fcntl.flock`` on ``ROOT/locks/<key>.lock``, released by the kernel when its holder dies (a killed
writer never wedges the next one); each holder also leaves a record ``pid host start what`` in
``ROOT/locks/<key>.holders/`` for the refusal line, removed when it releases (a record whose process is gone on
this host is ignored). A root on S3 has ``LeaseLocks`` (``pipeline.leases``): lease objects with an expiry.
"""
from __future__ import annotations

import errno
import fcntl
import os
import secrets
import socket
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import ContextManager, Iterator, Protocol

from pipeline.errors import RunLockedError
from pipeline.holds import reentrant_hold, this_command
from pipeline.names import check_name
from pipeline.storage import Store, locks_dir, root_of_map

ROOT_KEY = "root"


def map_key(name: str) -> str:
    """The lock key of map ``name``."""
    return f"map-{check_name(name, 'map', '--map')}"


class Locks(Protocol):
    """The lock service of one output root."""

    def hold(self, key: str, *, exclusive: bool, what: str | None = None) -> ContextManager[None]:
        """Hold lock ``key`` (shared or exclusive) for the ``with`` block; RunLockedError at once when taken."""


@dataclass
class _Held:
    fd: int
    exclusive: bool
    count: int
    record: Path


_HELD: dict[Path, _Held] = {}  # this process's locks, by lock file
_HELD_LOCK = threading.Lock()


class FileLocks:
    """``fcntl.flock`` locks under ``ROOT/locks/`` (local or NFS file systems)."""

    def __init__(self, root: Path | str):
        self.dir = locks_dir(Path(root))

    @contextmanager
    def hold(self, key: str, *, exclusive: bool, what: str | None = None) -> Iterator[None]:
        path = (self.dir / f"{key}.lock").absolute()

        def release(held: _Held) -> None:
            held.record.unlink(missing_ok=True)
            os.close(held.fd)

        with reentrant_hold(_HELD, _HELD_LOCK, path, exclusive, str(path),
                            lambda: self._acquire(path, exclusive, what or this_command()), release):
            yield

    def _acquire(self, path: Path, exclusive: bool, what: str) -> _Held:
        self.dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise RunLockedError(self._refusal(path, exclusive, what)) from exc
        except BaseException:
            os.close(fd)
            raise
        holders = path.with_suffix(".holders")
        holders.mkdir(exist_ok=True)
        if exclusive:  # no one else holds it: records left by killed holders go
            for stale in holders.iterdir():
                stale.unlink(missing_ok=True)
        record = holders / f"{socket.gethostname()}.{os.getpid()}.{secrets.token_hex(4)}"
        start = datetime.now(timezone.utc).isoformat(timespec="seconds")
        tmp = record.with_name("." + record.name)
        tmp.write_text(f"pid={os.getpid()} host={socket.gethostname()} start={start} "
                       f"{'exclusive' if exclusive else 'shared'}: {what}\n", encoding="utf-8")
        tmp.replace(record)
        return _Held(fd, exclusive, 1, record)

    def _refusal(self, path: Path, exclusive: bool, what: str) -> str:
        live = _live_records(path.with_suffix(".holders"))
        holder = live[0] if live else "a holder that left no record (another host, or one starting or ending now)"
        more = f" (and {len(live) - 1} more)" if len(live) > 1 else ""
        return (f"{path}: held by {holder}{more}; `{what}` needs it {'exclusive' if exclusive else 'shared'} and "
                "stopped without writing. hint: try again when that one has ended (exit 75 = try later)")


def _live_records(holders: Path) -> list[str]:
    """The holder records under ``holders`` whose process still runs (or runs on another host), oldest first."""
    out = []
    try:
        entries = sorted(holders.iterdir(), key=lambda p: p.stat().st_mtime)
    except OSError:
        return out
    here = socket.gethostname()
    for rec in entries:
        if rec.name.startswith("."):
            continue
        try:
            host, pid, _ = rec.name.rsplit(".", 2)
            text = rec.read_text(encoding="utf-8", errors="replace").strip()
            alive = host != here or _pid_alive(int(pid))
        except (OSError, ValueError):
            continue
        if not alive:
            continue
        out.append(text[:400])
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def locks_for(root: Path | str | Store) -> Locks:
    """The lock service of output root ``root``: ``flock`` files for a local folder, leases on an object store
    (``pipeline.leases``)."""
    store = root if isinstance(root, Store) else None
    if store is None and isinstance(root, str) and "://" in root:
        store = Store.open(root)
    if store is None or store.local:
        return FileLocks(store.root if store is not None else root)
    from pipeline.leases import LeaseLocks

    return LeaseLocks(store)


@contextmanager
def writer_locks(root: Path | str, map_name: str | None, what: str | None = None) -> Iterator[None]:
    """What a writer of datasets holds: ``root`` shared, and map ``map_name`` exclusive when it publishes one."""
    locks = locks_for(root)
    with locks.hold(ROOT_KEY, exclusive=False, what=what):
        if map_name is None:
            yield
        else:
            with locks.hold(map_key(map_name), exclusive=True, what=what):
                yield


@contextmanager
def map_lock(mdir: Path, what: str | None = None) -> Iterator[None]:
    """Map ``ROOT/maps/NAME`` exclusive (publishing, moving LATEST), without the root lock (``tiles rollback``)."""
    mdir = Path(mdir)
    with locks_for(root_of_map(mdir)).hold(map_key(mdir.name), exclusive=True, what=what):
        yield


@contextmanager
def root_exclusive(root: Path | str, what: str | None = None) -> Iterator[None]:
    """The whole root, no run writing in it (``gc --apply``)."""
    with locks_for(root).hold(ROOT_KEY, exclusive=True, what=what):
        yield


def published_map(workflow, only: list[str] | None = None) -> str | None:
    """The map a workflow run writes: its ``map_name`` when a selected stage outputs a ``published`` dataset (the
    map's versions, e.g. ``map_tiles``), else None."""
    catalog = workflow.catalog.datasets
    for name, decl in workflow.stages.items():
        if only is not None and name not in only:
            continue
        if any(getattr(catalog.get(ds), "versioning", None) == "published" for ds in decl.outputs.values()):
            return workflow.spec.map_name
    return None


@contextmanager
def workflow_locks(workflow, root: Path, only: list[str] | None = None, *, dry_run: bool = False) -> Iterator[None]:
    """The locks of one workflow run (``pipeline.api.execute_workflow``): ``writer_locks`` of its root and of the map
    it publishes; none for a dry run (it only reads)."""
    if dry_run:
        yield
        return
    with writer_locks(root, published_map(workflow, only)):
        yield
