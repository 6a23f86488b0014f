"""Published maps on any store: committing versions to an object store, and reading them back (knows nothing about
LiDAR; the local protocol is ``pipeline.versioned``).

Commit on an object store (``push_version``): every file of the version is uploaded under ``maps/NAME/vNNNN/``, then
its ``manifest.json`` is created with ``If-None-Match: *``, last: a version without its manifest is not a version
(``list_versions`` skips it; ``cornermap gc`` removes it), and a second writer of the same number is refused
(``PublishConflictError``). ``LATEST`` is one PUT after that (atomic: a reader sees the old line or the new one).
A writer killed at any point leaves LATEST naming the previous complete version. The map's exclusive lock is a lease
(``pipeline.leases``).

Reading (``readable_root``): a command that reads published versions (``tiles ls|log|verify|export``, ``maps show``,
``mapformat.loader.open_map``) sees a read-only local snapshot of what it needs, downloaded from the bucket into a
temporary folder (never one named after the root): LATEST, map.json, gate/, every committed manifest, and the
versions it reads whole. Verification hashes the downloaded bytes: what is checked is what the bucket holds.
"""
from __future__ import annotations

import contextlib
import hashlib
import logging
import tempfile
from pathlib import Path, PurePath
from typing import Any, Callable, Iterable, Iterator, Mapping

from pipeline import storage
from pipeline.errors import PublishConflictError, UnknownNameError
from pipeline.storage import Store

log = logging.getLogger(__name__)


def list_versions(store: Store, mdir: PurePath) -> list[int]:
    """Committed versions of a map on ``store`` (their manifest exists), ascending."""
    out = []
    for name in store.listdir(mdir):
        m = storage.VERSION_RE.match(name)
        if m and store.exists(storage.version_manifest(mdir / name)):
            out.append(int(m.group(1)))
    return sorted(out)


def map_names(store: Store) -> list[str]:
    return [n for n in store.listdir(storage.maps_dir(store.root)) if not n.startswith(".")]


def resolve_map(store: Store, name: str | None, hint: str = "pass --map NAME (and --root ROOT)") -> str:
    """``name`` when the map exists on ``store``; the only map with no name; UnknownNameError otherwise."""
    from pipeline.names import check_name, suggest

    have = map_names(store)
    where = store.url(storage.maps_dir(store.root))
    if name is None:
        if len(have) != 1:
            raise UnknownNameError(f"{where}: {'no maps' if not have else 'several maps: ' + ', '.join(have)}; "
                                   f"hint: {hint}")
        return have[0]
    check_name(name, "map", "--map")
    if name not in have:
        raise UnknownNameError(f"{where}: no map {name!r}; have {', '.join(have) or 'none'}{suggest(name, have)}; "
                               "hint: --root is the root holding maps/NAME")
    return name


def push_version(store: Store, mdir: PurePath, local_vdir: Path, number: int) -> str:
    """Commit the complete local version ``local_vdir`` as ``vNNNN`` of ``mdir`` on ``store``: its files, then its
    manifest (byte for byte, so the digest chain holds) created last and conditionally. Returns the manifest's
    sha256; PublishConflictError when that version is already committed there."""
    vdir = storage.version_dir(mdir, number)
    manifest_loc = storage.version_manifest(vdir)
    if store.exists(manifest_loc):
        raise PublishConflictError(f"{store.url(vdir)}: already committed; a published version is never overwritten")
    raw = storage.version_manifest(Path(local_vdir)).read_bytes()
    for path in sorted(p for p in Path(local_vdir).rglob("*") if p.is_file()):
        rel = path.relative_to(local_vdir).as_posix()
        if rel != storage.VERSION_MANIFEST:
            store.upload_file(path, vdir / rel)
    if not store.create(manifest_loc, raw):
        raise PublishConflictError(f"{store.url(vdir)}: another writer committed it first; this one stops")
    return hashlib.sha256(raw).hexdigest()


def push_map(local_root: Path, name: str, store: Store, say: Callable[[str], None] | None = None) -> list[int]:
    """Publish map ``name`` of the local root ``local_root`` to ``store``: each complete local version not yet
    committed there (oldest first, each through ``push_version``), the identity and gate records, then LATEST as the
    local one names it. Idempotent (a second push commits nothing). Holds the store's map lock (a lease on S3).
    Returns the versions committed."""
    from pipeline.locks import locks_for, map_key
    from pipeline.version_read import list_versions as local_versions
    from pipeline.version_read import read_latest_entry

    src = storage.map_dir(Path(local_root), name)
    dst = storage.map_dir(store.root, name)
    entry = read_latest_entry(src)
    if entry is None:
        raise UnknownNameError(f"{src}: nothing published yet (no {storage.LATEST} file)")
    pushed = []
    with locks_for(store).hold(map_key(name), exclusive=True):
        have = set(list_versions(store, dst))
        for v in local_versions(src):
            if v in have:
                continue
            push_version(store, dst, storage.version_dir(src, v), v)
            pushed.append(v)
            if say:
                say(f"committed {store.url(storage.version_dir(dst, v))}")
        for loc in (storage.identity_file(src), *sorted(Path(storage.gate_dir(src)).glob("*.json"))):
            if Path(loc).is_file():
                store.put_bytes(dst / Path(loc).relative_to(src).as_posix(), Path(loc).read_bytes())
        store.put_bytes(storage.latest_file(dst), storage.latest_file(src).read_bytes())
    return pushed


def read_latest_number(store: Store, name: str) -> int | None:
    """The version map ``name``'s LATEST names on ``store``, None before the first publish."""
    from pipeline.version_read import read_latest

    with tempfile.TemporaryDirectory(prefix="cornermap-latest-") as tmp:
        try:
            raw = store.read_bytes(storage.latest_file(storage.map_dir(store.root, name)))
        except FileNotFoundError:
            return None
        mdir = storage.map_dir(Path(tmp), name)
        mdir.mkdir(parents=True)
        storage.latest_file(mdir).write_bytes(raw)
        return read_latest(mdir)  # its parser and its one-line errors


def publish_version_to(store: Store, name: str, write: Callable[[Path], Mapping[str, Any]], *,
                       locked: bool = False, whole: Iterable[int] | str = (), **kwargs: Any):
    """``pipeline.versioned.publish_version`` onto ``store``: the version is written and checked in a local staging
    collection that holds the map's current LATEST and manifests (so numbering and the digest chain continue), and
    the versions ``whole`` names in full (``"latest"``: what a writer reading its parent needs), then committed with
    ``push_version`` and LATEST moved, under the map's lease (``locked``: the caller's run holds it already, as a
    build's task does). ``write(staging)``'s map folder is ``staging.parent``. Returns the ``PublishedVersion``."""
    from pipeline.locks import locks_for, map_key
    from pipeline.versioned import publish_version

    dst = storage.map_dir(store.root, name)
    hold = contextlib.nullcontext() if locked else locks_for(store).hold(map_key(name), exclusive=True)
    with hold, tempfile.TemporaryDirectory(prefix="cornermap-publish-", dir=storage.scratch_base()) as tmp:
        local_mdir = storage.map_dir(Path(tmp), name)
        snapshot_map(store, name, Path(tmp), whole=whole)
        pv = publish_version(local_mdir, write, **kwargs)
        if pv.created:
            push_version(store, dst, pv.path, pv.version)
            if kwargs.get("move_latest", True):
                store.put_bytes(storage.latest_file(dst), storage.latest_file(local_mdir).read_bytes())
        from dataclasses import replace

        return replace(pv, path=storage.version_dir(dst, pv.version))


def snapshot_map(store: Store, name: str, dest: Path, whole: Iterable[int] | str = "latest",
                 pick: Callable[[dict], list[str]] | None = None) -> Path:
    """Download map ``name``'s LATEST, identity, gate records and every committed manifest into ``dest`` (a local
    root), the versions ``whole`` names in full (``"all"``, ``"latest"``, or numbers), and of the others the files
    ``pick(manifest)`` names (a changelog, trajectories). Returns the local map folder."""
    import json

    from pipeline.names import inside

    src = storage.map_dir(store.root, name)
    mdir = storage.map_dir(Path(dest), name)
    mdir.mkdir(parents=True, exist_ok=True)
    for loc in (storage.latest_file(src), storage.identity_file(src)):
        with contextlib.suppress(FileNotFoundError):
            (mdir / loc.name).write_bytes(store.read_bytes(loc))
    store.download_tree(storage.gate_dir(src), storage.gate_dir(mdir))
    versions = list_versions(store, src)
    if whole == "all":
        full = set(versions)
    elif whole == "latest":
        from pipeline.version_read import read_latest

        latest = read_latest(mdir)
        full = {latest} if latest is not None else set()
    else:
        full = set(whole)
    for v in versions:
        local_v = storage.version_dir(mdir, v)
        if v in full:
            store.download_tree(storage.version_dir(src, v), local_v)
        else:
            local_v.mkdir(parents=True, exist_ok=True)
            raw = store.read_bytes(storage.version_manifest(storage.version_dir(src, v)))
            storage.version_manifest(local_v).write_bytes(raw)
            try:
                wanted = pick(json.loads(raw)) if pick is not None else []
            except (ValueError, TypeError, KeyError, AttributeError):
                wanted = []  # a malformed manifest: the reader names it
            for rel in wanted:
                target = inside(local_v, rel)
                target.parent.mkdir(parents=True, exist_ok=True)
                with contextlib.suppress(FileNotFoundError):
                    target.write_bytes(store.read_bytes(storage.version_dir(src, v) / rel))
    return mdir


@contextlib.contextmanager
def readable_root(root: str | Path, name: str | None, whole: Iterable[int] | str = "latest",
                  version: str | int | None = None, pick: Callable[[dict], list[str]] | None = None
                  ) -> Iterator[tuple[Path, Callable[[str], str]]]:
    """(a local root to read map ``name`` from, a function that turns local paths in messages back into the root's
    URIs). A local root is itself (no copy); an ``s3://`` root is a snapshot (``snapshot_map``) in a temporary
    folder, removed after. ``version`` ("LATEST", "v0003", 3) adds that version to ``whole``."""
    store = Store.open(root)
    if store.local:
        yield Path(root), (lambda text: text)
        return
    name = resolve_map(store, name)
    with tempfile.TemporaryDirectory(prefix="cornermap-view-") as tmp:
        if version is not None and not (isinstance(version, str) and version.upper() == "LATEST"):
            from pipeline.version_read import parse_version

            whole = whole if whole == "all" else [parse_version(version)]
        snapshot_map(store, name, Path(tmp), whole, pick)
        prefix = str(Path(tmp))
        yield Path(tmp), (lambda text: text.replace(prefix, store.uri))


def _newest_modified(store: Store, loc: PurePath) -> float:
    """The newest modification time (unix s) of the objects under ``loc`` (0 when there is none)."""
    import os as _os

    if store.local:
        times = [p.stat().st_mtime for p in Path(loc).rglob("*") if p.is_file()]
        return max(times, default=0.0) if times else (_os.stat(loc).st_mtime if Path(loc).exists() else 0.0)
    return max((stamp for _, stamp in store.walk_objects(loc).values()), default=0.0)


def gc_uncommitted(store: Store, min_age_h: float, apply: bool) -> list[tuple[str, str]]:
    """``cornermap gc`` on an object-store root: the version prefixes without their manifest (uploads of a killed
    push) untouched for ``min_age_h``, and lock records whose lease expired more than ``min_age_h`` ago. Deleting
    holds the root's lock exclusive (a lease). Returns (URI, why) of what was (or would be) removed."""
    import json
    import time

    from pipeline.locks import ROOT_KEY, locks_for

    def plan() -> list[tuple[PurePath, str, str | None]]:
        """(location, why, ETag of a lock record) of what is to go."""
        now, out = time.time(), []
        for name in map_names(store):
            mdir = storage.map_dir(store.root, name)
            for entry in store.listdir(mdir):
                if not storage.VERSION_RE.match(entry) or store.exists(storage.version_manifest(mdir / entry)):
                    continue
                if now - _newest_modified(store, mdir / entry) >= min_age_h * 3600:
                    out.append((mdir / entry, "uncommitted version: no manifest, a killed writer's uploads", None))
        locks = storage.locks_dir(store.root)
        for lock in store.listdir(locks):
            for rec in store.listdir(locks / lock):
                try:
                    tag = store.etag(locks / lock / rec)
                    expires = float(json.loads(store.read_bytes(locks / lock / rec)).get("expires_unix", 0.0))
                except (FileNotFoundError, ValueError, AttributeError):
                    continue
                if tag is not None and now - expires >= min_age_h * 3600:
                    out.append((locks / lock / rec, "lease expired: its holder is gone", tag))
        return out

    found = plan()
    if apply and found:
        with locks_for(store).hold(ROOT_KEY, exclusive=True, what="cornermap gc --apply"):
            found = plan()  # again under the lock: only what is still there, still uncommitted, still expired
            for loc, _, tag in found:
                if tag is not None:
                    store.delete_if(loc, tag)  # a lease renewed or taken over since has another ETag: kept
                else:
                    store.delete_tree(loc)
    return [(store.url(loc), why) for loc, why, _ in found]


def rollback(store: Store, name: str, to: str | int) -> tuple[int | None, int]:
    """Point the bucket's LATEST of map ``name`` at an older committed version after verifying its bytes (one PUT;
    nothing is deleted), under the map's lease. Returns (previous LATEST, new LATEST); ChecksumError when the
    version is not intact, UnknownNameError when it is not committed."""
    from pipeline.errors import ChecksumError
    from pipeline.locks import locks_for, map_key
    from pipeline.version_read import parse_version, read_latest, read_manifest, verify_version, version_name

    name = resolve_map(store, name)
    number = parse_version(to)
    mdir = storage.map_dir(store.root, name)
    have = list_versions(store, mdir)
    if number not in have:
        raise UnknownNameError(f"{store.url(mdir)}: no version {version_name(number)}; have "
                               f"{', '.join(version_name(v) for v in have) or 'none'}")
    with locks_for(store).hold(map_key(name), exclusive=True), \
            tempfile.TemporaryDirectory(prefix="cornermap-view-") as tmp:
        local = snapshot_map(store, name, Path(tmp), [number])
        vdir = storage.version_dir(local, number)
        problems = verify_version(vdir)
        if problems:
            raise ChecksumError(f"{store.url(storage.version_dir(mdir, number))}: {len(problems)} integrity "
                                f"problem(s), not rolled back to: {problems[0].replace(str(tmp), store.uri)}")
        before = read_latest(local)
        sha = read_manifest(vdir)[1]
        store.put_bytes(storage.latest_file(mdir), f"{version_name(number)} {sha}\n".encode())
    return before, number


def map_location(root: str | Path, name: str | None) -> str | Path:
    """Where ``mapformat.loader.open_map`` finds map ``name`` of ``root``: ``ROOT/maps/NAME`` for a local root, its
    ``s3://`` URI for a bucket (the only map when ``name`` is None; UnknownNameError otherwise)."""
    store = Store.open(root)
    if store.local:
        from pipeline.names import published_map_dir

        return published_map_dir(root, name, hint="pass --map NAME (and --root ROOT)")
    return store.url(storage.map_dir(store.root, resolve_map(store, name)))


def publish_map_version(root: str | Path, name: str, write: Callable[[Path], Mapping[str, Any]], **kwargs: Any):
    """A build's publish of map ``name`` on its output root (a stage's task: the run holds the map's lock):
    ``pipeline.versioned.publish_version`` in ``ROOT/maps/NAME`` on a local root; on an object store
    ``publish_version_to`` with LATEST's version downloaded whole (a writer reads its parent). ``write(staging)``'s
    map folder (its parent's files) is ``staging.parent``. Returns the ``PublishedVersion``."""
    store = Store.open(root)
    if store.local:
        from pipeline.versioned import publish_version

        return publish_version(storage.map_dir(Path(root), name), write, **kwargs)
    return publish_version_to(store, name, write, locked=True, whole="latest", **kwargs)


@contextlib.contextmanager
def map_view(root: str | Path, name: str) -> Iterator[Path]:
    """A local root to read map ``name``'s identity and LATEST version from before a build: the root itself, or for
    an object store a snapshot in a temporary folder (empty for a map not yet on the store)."""
    store = Store.open(root)
    if store.local:
        yield Path(root)
        return
    with tempfile.TemporaryDirectory(prefix="cornermap-view-") as tmp:
        snapshot_map(store, name, Path(tmp), whole="latest")
        yield Path(tmp)
