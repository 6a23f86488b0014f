"""Versioned, immutable directories with an atomic ``LATEST`` pointer (knows nothing about LiDAR).

Layout of one collection (e.g. ``ROOT/maps/NAME``)::

    NAME/
      LATEST            one line "vNNNN <sha256 of its manifest.json>\\n", replaced atomically (temp file +
                        fsync + os.replace); a file holding only "vNNNN" (before the digest) is still read
      .publish.lock     empty; an exclusive fcntl.flock held by the one publisher at work
      v0001/            immutable; manifest.json lists every other file with its sha256 and size
      v0002/ ...

Publishing (``publish_version``):
  1. take the lock without waiting (a second publisher fails at once with ``PublishConflictError`` and
     creates nothing); remove staging/trash directories that killed publishers left behind;
  2. the caller's ``write(staging_dir)`` writes the files and returns its manifest fields;
  3. every file is hashed, ``manifest.json`` is written last, then every checksum is re-read and verified;
  4. files and directories are fsynced, the staging directory is renamed to ``vNNNN`` (never onto an
     existing one), then ``LATEST`` is replaced;
     Each manifest records ``parent_manifest_sha256``, so LATEST's digest vouches for the newest manifest
     and each manifest for its parent's: an edited manifest anywhere in the chain is detected.
  5. retention removes the oldest versions beyond ``keep_last``, never the one ``LATEST`` names.
A process killed at any point leaves ``LATEST`` naming the previous complete version (or absent).
The flock is released by the kernel when its holder dies, so a killed publisher never wedges the next one.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import logging
import os
import secrets
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

from pipeline.errors import DatasetIOError, PublishConflictError
from pipeline.fingerprint import file_sha256
from pipeline.storage import PUBLISH_LOCK
from pipeline.version_read import (  # noqa: F401 - re-exported: the publishing API in one module
    _VERSION_RE,
    LATEST_NAME,
    MANIFEST_NAME,
    MAX_MANIFEST_BYTES,
    check_version,
    list_versions,
    parse_version,
    read_latest,
    read_latest_entry,
    read_manifest,
    resolve_version,
    trusted_manifest_digests,
    verify_version,
    version_name,
)

log = logging.getLogger(__name__)

LOCK_NAME = PUBLISH_LOCK
_STAGING_PREFIX = ".staging-"
_TRASH_PREFIX = ".trash-"


@dataclass(frozen=True)
class PublishedVersion:
    """One complete version of a collection."""

    version: int
    path: Path
    manifest_sha256: str
    manifest: dict[str, Any]
    created: bool  # False when an existing version was returned instead of publishing

    @property
    def name(self) -> str:
        return version_name(self.version)


@contextmanager
def publish_lock(collection_dir: Path) -> Iterator[None]:
    """Exclusive, non-waiting publisher lock; released by the kernel if the holder dies."""
    collection_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(collection_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise PublishConflictError(
                    f"{collection_dir}: another publisher holds {LOCK_NAME}; this one stops without writing. "
                    "hint: wait for it to finish, then run again (a no-op if its inputs were the same)") from exc
            raise
        yield
    finally:
        os.close(fd)


def _fsync_path(path: Path, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove_leftovers(collection_dir: Path) -> None:
    """Staging/trash dirs can only be leftovers of dead publishers: we hold the lock."""
    for entry in os.scandir(collection_dir):
        if entry.name.startswith((_STAGING_PREFIX, _TRASH_PREFIX)):
            log.warning("removing %s left by an interrupted publisher", entry.path)
            shutil.rmtree(entry.path, ignore_errors=False)
        elif entry.name.startswith(f".{LATEST_NAME}.tmp"):
            os.unlink(entry.path)


def write_latest(collection_dir: Path, version: int, durable: bool = True, manifest_sha256: str | None = None) -> None:
    """Point LATEST at ``version`` with its manifest's digest (read from disk when not given)."""
    collection_dir = Path(collection_dir)
    if manifest_sha256 is None:
        manifest_sha256 = read_manifest(collection_dir / version_name(version))[1]
    tmp = collection_dir / f".{LATEST_NAME}.tmp-{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(f"{version_name(version)} {manifest_sha256}\n")
        fh.flush()
        if durable:
            os.fsync(fh.fileno())
    os.replace(tmp, collection_dir / LATEST_NAME)
    if durable:
        _fsync_path(collection_dir, directory=True)


def _hash_tree(staging: Path, durable: bool) -> dict[str, dict[str, Any]]:
    files = {}
    for path in sorted(p for p in staging.rglob("*") if p.is_file()):
        rel = path.relative_to(staging).as_posix()
        if rel == MANIFEST_NAME:
            raise DatasetIOError(f"{path}: the writer must not create {MANIFEST_NAME}; the publisher writes it")
        if durable:
            _fsync_path(path)
        files[rel] = {"sha256": file_sha256(path), "bytes": path.stat().st_size}
    return files


def apply_retention(collection_dir: Path, keep_last: int) -> list[int]:
    """Delete the oldest versions beyond keep_last, never the one LATEST names; call under publish_lock."""
    latest = read_latest(collection_dir)
    versions = list_versions(collection_dir)
    doomed = [v for v in versions[:max(0, len(versions) - keep_last)] if v != latest]
    for v in doomed:
        trash = collection_dir / f"{_TRASH_PREFIX}{version_name(v)}-{secrets.token_hex(4)}"
        os.rename(collection_dir / version_name(v), trash)  # the version vanishes atomically
        shutil.rmtree(trash)
        log.info("retention: removed %s of %s (keep_last=%d)", version_name(v), collection_dir, keep_last)
    return doomed


def publish_version(collection_dir: Path, write: Callable[[Path], Mapping[str, Any]], *,
                    keep_last: int | None = None, durable: bool = True,
                    reuse: Callable[[dict[str, Any]], bool] | None = None,
                    move_latest: bool = True) -> PublishedVersion:
    """Publish ``write``'s files as the next version and point ``LATEST`` at it.

    ``write(staging_dir)`` writes files under staging_dir and returns JSON-able manifest fields; the
    publisher adds ``version``, ``parent_version``, ``created_utc`` and ``files``. ``reuse(latest_manifest)``
    returning True skips publishing and returns the latest version (idempotent rebuilds). ``move_latest=False``
    writes the complete version but leaves ``LATEST`` where it was (a candidate: a later check moves LATEST
    with ``write_latest``, or leaves it unpublished).
    """
    collection_dir = Path(collection_dir)
    if keep_last is not None and keep_last < 1:
        raise ValueError(f"keep_last must be >= 1 (LATEST is always kept); got {keep_last}")
    with publish_lock(collection_dir):
        _remove_leftovers(collection_dir)
        parent = read_latest(collection_dir)
        parent_sha = read_manifest(collection_dir / version_name(parent))[1] if parent is not None else None
        if parent is not None and reuse is not None:
            parent_dir = collection_dir / version_name(parent)
            manifest, sha = read_manifest(parent_dir)
            if reuse(manifest):
                log.info("%s: inputs unchanged since %s; not publishing", collection_dir, version_name(parent))
                return PublishedVersion(parent, parent_dir, sha, manifest, created=False)
        existing = list_versions(collection_dir)
        number = max(existing + [parent or 0]) + 1
        final = collection_dir / version_name(number)
        staging = collection_dir / f"{_STAGING_PREFIX}{version_name(number)}-{os.getpid()}-{secrets.token_hex(4)}"
        staging.mkdir()
        try:
            fields = dict(write(staging))
            reserved = {"version", "parent_version", "parent_manifest_sha256", "created_utc", "files"} & set(fields)
            if reserved:
                raise ValueError(f"writer returned reserved manifest keys {sorted(reserved)}")
            files = _hash_tree(staging, durable)
            manifest = {**fields, "version": number, "parent_version": parent, "parent_manifest_sha256": parent_sha,
                        "created_utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                        "files": files}
            raw = json.dumps(manifest, indent=1, sort_keys=False).encode("utf-8")
            with open(staging / MANIFEST_NAME, "wb") as fh:
                fh.write(raw)
                fh.flush()
                if durable:
                    os.fsync(fh.fileno())
            check_version(staging)
            if durable:
                for d in sorted({p.parent for p in staging.rglob("*")} | {staging}, key=lambda p: -len(p.parts)):
                    _fsync_path(d, directory=True)
            if final.exists():  # impossible under the lock unless someone wrote by hand; never overwrite
                raise PublishConflictError(f"{final}: already exists; a published version is never overwritten")
            os.rename(staging, final)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        if durable:
            _fsync_path(collection_dir, directory=True)
        if move_latest:
            write_latest(collection_dir, number, durable, hashlib.sha256(raw).hexdigest())
        if keep_last is not None:
            apply_retention(collection_dir, keep_last)
        log.info("published %s (%d files)", final, len(files))
        return PublishedVersion(number, final, hashlib.sha256(raw).hexdigest(), manifest, created=True)


def rollback_latest(mdir: Path, to: str) -> tuple[int | None, int]:
    """Point LATEST at an older complete, verified version (a new LATEST write; nothing is deleted).
    Returns (previous LATEST, new LATEST)."""
    from pipeline.errors import ChecksumError, UnknownNameError
    from pipeline.locks import map_lock

    number = parse_version(to)
    vdir = Path(mdir) / version_name(number)
    if not vdir.is_dir():
        have = ", ".join(version_name(v) for v in list_versions(mdir)) or "none"
        raise UnknownNameError(f"{mdir}: no version {version_name(number)}; have {have}")
    with map_lock(Path(mdir)), publish_lock(Path(mdir)):
        problems = verify_version(vdir)
        if problems:
            raise ChecksumError(f"{vdir}: {len(problems)} integrity problem(s), not rolled back to: {problems[0]}")
        before = read_latest(mdir)
        write_latest(Path(mdir), number)
    return before, number
