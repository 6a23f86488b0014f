"""Locks of a root on object storage: lease objects with an expiry (the S3 backend of ``pipeline.locks``).

An object store has no ``flock`` and no process that the kernel could see die, so a lock is an object that says
who holds it and until when, renewed while the holder lives (``docs/storage.md``, "Locks on object storage")::

    locks/<key>.lock/x              the exclusive holder's record, created with If-None-Match: * (one winner)
    locks/<key>.lock/s-<holder>     one record per shared holder

A record is JSON ``{holder, host, pid, what, exclusive, expires_unix, ttl_s}``. Its holder rewrites it every
``ttl_s / 3`` seconds (a daemon thread; the exclusive record with If-Match on its own ETag, so a renewal never
overwrites a successor). A record whose ``expires_unix`` has passed belongs to a dead (or stalled) holder:

- exclusive ``x`` expired: the next writer takes it over with a conditional replace (If-Match on the expired
  record's ETag); of several takers exactly one wins, the others are refused (exit 75);
- shared ``s-*`` expired: ignored, and removed by the next exclusive taker.

Taking ``x`` then finding a live shared record (or taking a shared record then finding a live ``x``) gives the lock
back and refuses: of two writers that race, at most one proceeds (both may be refused; exit 75 means try later).
A holder that could not renew for longer than ``ttl_s`` (a stalled machine) has lost its lock: the renewal thread logs
it, and what it publishes afterwards still goes through conditional commit markers (a version number is committed
once). Expiry is judged on each machine's clock: clocks must agree to well under ``ttl_s`` (NTP does).
``CORNERMAP_LEASE_TTL_S`` sets ``ttl_s`` (default 60 s).
"""
from __future__ import annotations

import json
import logging
import os
import secrets
import socket
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import PurePath
from typing import Iterator

from pipeline.errors import RunLockedError
from pipeline.holds import reentrant_hold, this_command
from pipeline.storage import Store, locks_dir

log = logging.getLogger(__name__)
DEFAULT_TTL_S = 60.0
EXCLUSIVE = "x"
SHARED_PREFIX = "s-"
_PROCESS_TOKEN = secrets.token_hex(4)


def lease_ttl_s() -> float:
    try:
        return max(0.5, float(os.environ.get("CORNERMAP_LEASE_TTL_S", DEFAULT_TTL_S)))
    except ValueError:
        return DEFAULT_TTL_S


@dataclass
class _Lease:
    loc: PurePath
    exclusive: bool
    count: int
    etag: str | None
    stop: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    lost: bool = False


_HELD: dict[tuple[str, str, str], _Lease] = {}  # (store, key, holder): nested holds of one process share a lease
_HELD_LOCK = threading.Lock()


class LeaseLocks:
    """``hold(key, exclusive=..., what=...)`` on a ``Store`` without file locks (S3)."""

    def __init__(self, store: Store, ttl_s: float | None = None, holder: str | None = None):
        self.store = store
        self.dir = locks_dir(store.root)
        self.ttl_s = lease_ttl_s() if ttl_s is None else ttl_s
        # one holder per process (a rebuild holds the map, then runs its build in the same process); tests name more
        self.holder = holder or f"{socket.gethostname()}.{os.getpid()}.{_PROCESS_TOKEN}"

    def _record(self, exclusive: bool, what: str) -> bytes:
        now = time.time()
        return json.dumps({"holder": self.holder, "host": socket.gethostname(), "pid": os.getpid(), "what": what,
                           "exclusive": exclusive, "ttl_s": self.ttl_s, "expires_unix": now + self.ttl_s,
                           "start_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}).encode()

    def _read(self, loc: PurePath) -> dict | None:
        try:
            doc = json.loads(self.store.read_bytes(loc))
        except FileNotFoundError:
            return None
        except ValueError:
            return {"what": "an unreadable lock record", "expires_unix": 0.0}
        return doc if isinstance(doc, dict) else {"expires_unix": 0.0}

    @staticmethod
    def _live(doc: dict | None) -> bool:
        return doc is not None and float(doc.get("expires_unix", 0.0)) > time.time()

    def _refuse(self, key: str, doc: dict, exclusive: bool, what: str) -> RunLockedError:
        left = float(doc.get("expires_unix", 0.0)) - time.time()
        holder = (f"pid={doc.get('pid')} host={doc.get('host')} start={doc.get('start_utc')} "
                  f"{'exclusive' if doc.get('exclusive') else 'shared'}: {doc.get('what')}")
        return RunLockedError(f"{self.store.url(self.dir / (key + '.lock'))}: held by {holder} (its lease runs "
                              f"{max(left, 0):.0f} s more unless renewed); `{what}` needs it "
                              f"{'exclusive' if exclusive else 'shared'} and stopped without writing. hint: try again "
                              "when that one has ended (exit 75 = try later)")

    @contextmanager
    def hold(self, key: str, *, exclusive: bool, what: str | None = None) -> Iterator[None]:
        what = what or this_command()

        def acquire() -> _Lease:
            lease = self._acquire_exclusive(key, what) if exclusive else self._acquire_shared(key, what)
            lease.thread = threading.Thread(target=self._renew, args=(lease, what), daemon=True,
                                            name=f"lease-{key}")
            lease.thread.start()
            return lease

        def release(lease: _Lease) -> None:
            lease.stop.set()
            lease.thread.join()
            self._release(lease)

        with reentrant_hold(_HELD, _HELD_LOCK, (self.store.uri, key, self.holder), exclusive, key, acquire, release):
            yield

    def _acquire_exclusive(self, key: str, what: str) -> _Lease:
        base = self.dir / f"{key}.lock"
        loc = base / EXCLUSIVE
        body = self._record(True, what)
        if not self.store.create(loc, body):
            etag = self.store.etag(loc)
            doc = self._read(loc)
            if self._live(doc):
                raise self._refuse(key, doc, True, what)
            if etag is None or not self.store.replace_if(loc, body, etag):  # another taker won the expired lease
                doc = self._read(loc) or {}
                raise self._refuse(key, doc, True, what)
            log.warning("%s: took over an expired lease of %s", self.store.url(loc), (doc or {}).get("what"))
        etag = self.store.etag(loc)
        for name in self.store.listdir(base):
            if not name.startswith(SHARED_PREFIX):
                continue
            doc = self._read(base / name)
            if self._live(doc):
                if etag is not None:
                    self.store.delete_if(loc, etag)
                raise self._refuse(key, doc, True, what)
            self.store.delete(base / name)  # a dead shared holder's record
        return _Lease(loc, True, 1, etag)

    def _acquire_shared(self, key: str, what: str) -> _Lease:
        base = self.dir / f"{key}.lock"
        loc = base / f"{SHARED_PREFIX}{self.holder}"
        self.store.put_bytes(loc, self._record(False, what))
        doc = self._read(base / EXCLUSIVE)
        if self._live(doc):
            self.store.delete(loc)
            raise self._refuse(key, doc, False, what)
        return _Lease(loc, False, 1, None)

    def _renew(self, lease: _Lease, what: str) -> None:
        while not lease.stop.wait(self.ttl_s / 3):
            body = self._record(lease.exclusive, what)
            try:
                if lease.exclusive:
                    if lease.etag is None or not self.store.replace_if(lease.loc, body, lease.etag):
                        lease.lost = True
                        log.error("%s: lease lost (not renewed within %.0f s; another writer took it over)",
                                  self.store.url(lease.loc), self.ttl_s)
                        return
                    lease.etag = self.store.etag(lease.loc)
                else:
                    self.store.put_bytes(lease.loc, body)
            except OSError as exc:  # the store unreachable for a moment: try again at the next period
                log.warning("%s: lease renewal failed (%s); retrying", self.store.url(lease.loc), exc)

    def _release(self, lease: _Lease) -> None:
        try:
            if lease.exclusive:
                if lease.etag is not None and not lease.lost:
                    self.store.delete_if(lease.loc, lease.etag)
            else:
                self.store.delete(lease.loc)
        except OSError as exc:  # the lease then simply expires
            log.warning("%s: could not release the lease (%s); it expires in %.0f s", self.store.url(lease.loc),
                        exc, self.ttl_s)
