"""Drives on object storage: a drive file named by URI (``s3://bucket/.../drive.yaml``) and a local drive staged into
an object-store root, so that every task of a build reads its drive from the store, never from a client path.

A drive is a ``drive.yaml`` whose string values name its inputs relative to its folder (``pipeline.fingerprint``
takes every such value that names an existing file or folder). In a bucket they resolve in the same bucket:
``scans`` beside ``s3://b/city/d1/drive.yaml`` is the prefix ``s3://b/city/d1/scans/``; ``../survey/s.las`` is
``s3://b/city/survey/s.las``.

* ``stage_drive``: a local drive given to a build on an ``s3://`` root is uploaded once into
  ``ROOT/drives/<fp16>/`` (``storage.staged_drive_dir``; ``fp16`` its drive fingerprint: by content), the files
  keeping their places relative to each other, then its marker ``_staged.json`` last (a conditional put); a drive
  already staged (the marker is there) uploads nothing. The build's workflow then names the staged ``s3://`` URI.
* ``remote_drive_fingerprint``: a drive named by URI, by content and not by location: the drive file's sha256 and
  every object it names by relative name, size and ETag.
* ``local_drive``: what a task calls: a local path as is; a URI's drive fetched into this process's scratch
  (``storage.drive_copy_dir`` of its bucket: a dask worker's ``--local-directory``), only the objects absent or
  changed, and the local ``drive.yaml`` returned.
"""

from __future__ import annotations

import hashlib
import json
import os
import posixpath
import time
from pathlib import Path, PurePosixPath
from typing import Any

from pipeline import storage
from pipeline.errors import ConfigError, DatasetIOError
from pipeline.fingerprint import relative_strings

_STAGED: dict[tuple[str, str], str] = {}  # (root URI, local drive.yaml) -> staged drive.yaml URI, this process


def is_uri(value: object) -> bool:
    return storage.uri_scheme(value) is not None


def _split(uri: str) -> tuple[str, str]:
    """``s3://bucket/a/b`` -> (``s3://bucket``, ``a/b``)."""
    uri = storage.normalise_uri(uri)
    scheme, rest = uri.split("://", 1)
    bucket, _, key = rest.partition("/")
    return f"{scheme}://{bucket}", key


def _load(raw: bytes, where: str) -> Any:
    from pipeline.safe_yaml import MAX_YAML_BYTES, load_yaml

    if len(raw) > MAX_YAML_BYTES:
        return None
    try:
        return load_yaml(raw, where)
    except ConfigError:  # ingest names the problem when it reads the drive
        return None


def _read_drive_yaml(uri: str) -> tuple[storage.Store, PurePosixPath, bytes]:
    bucket_uri, key = _split(uri)
    store = storage.Store.open(bucket_uri)
    loc = store.root / key
    try:
        return store, loc, store.read_bytes(loc)
    except FileNotFoundError:
        raise ConfigError(
            storage.normalise_uri(uri),
            [
                "drive file not found in the object store; hint: list it "
                "with `aws s3 ls` (AWS_ENDPOINT_URL) or give the drive's "
                "local drive.yaml"
            ],
        ) from None


def _referenced(store: storage.Store, loc: PurePosixPath, raw: bytes) -> dict[str, dict[str, tuple[int, str, float]]]:
    """{value as written: {path relative to it ("" for a file): (bytes, tag)}} of every string value of the drive
    file that names an object or a prefix relative to its folder, in the same bucket."""
    bucket = loc.parts[0]
    folder = loc.parent.as_posix()
    found: dict[str, dict[str, tuple[int, str, float]]] = {}
    for value in relative_strings(_load(raw, storage.normalise_uri(f"s3://{loc.as_posix()}"))):
        target = posixpath.normpath(posixpath.join(folder, value))
        if target == bucket or not target.startswith(bucket + "/"):
            continue  # outside the bucket: not a drive input (ingest names a missing file)
        objects = store.objects_under(PurePosixPath(target))
        if objects:
            found[value] = objects
    return found


def read_drive_file(uri: str) -> bytes:
    """The bytes of a drive file in a bucket (ConfigError naming it when absent)."""
    return _read_drive_yaml(uri)[2]


def remote_drive_fingerprint(uri: str) -> str:
    """A drive named by URI by content, never by location (``fingerprint.drive_fingerprint``'s rule on objects): the
    drive file's sha256 and every object it names, by relative name, size and ETag."""
    from pipeline.fingerprint import stable_hash

    try:
        store, loc, raw = _read_drive_yaml(uri)
    except ConfigError:
        return stable_hash({"missing": storage.normalise_uri(uri).rsplit("/", 1)[-1]})
    refs = {
        name: sorted((rel, size, tag) for rel, (size, tag, _) in objs.items())
        for name, objs in _referenced(store, loc, raw).items()
    }
    return stable_hash({"drive_yaml": hashlib.sha256(raw).hexdigest(), "referenced_objects": refs})


def drive_exists(value: object) -> bool:
    """Whether a drive file (a local path or a URI) is there."""
    if not is_uri(value):
        return Path(str(value)).is_file()
    bucket_uri, key = _split(str(value))
    store = storage.Store.open(bucket_uri)
    return store.exists(store.root / key)


def drive_name(value: object) -> str:
    """A drive's name: its folder's (``.../drive_0/drive.yaml`` -> ``drive_0``)."""
    if is_uri(value):
        return storage.normalise_uri(value).rstrip("/").rsplit("/", 2)[-2]
    return Path(str(value)).resolve().parent.name


def local_drive(value: "str | Path") -> Path:
    """The local drive file a task reads: a local path as is; for a URI, the drive fetched into this process's scratch
    (the drive file and every object it names; those already there with their object's size and modification time
    are kept) and its local ``drive.yaml`` returned. DatasetIOError when an object cannot be read."""
    if not is_uri(value):
        return Path(value)
    from pipeline.store import use_local_copy

    uri = storage.normalise_uri(value)
    bucket_uri, key = _split(uri)
    copy = storage.drive_copy_dir(bucket_uri)
    use_local_copy(copy)
    store, loc, raw = _read_drive_yaml(uri)
    local_yaml = copy / key
    pairs, stamps = [], {}
    for value_, objects in _referenced(store, loc, raw).items():
        base = PurePosixPath(posixpath.normpath(posixpath.join(loc.parent.as_posix(), value_)))
        for rel, (size, _, stamp) in objects.items():
            src = base / rel if rel else base
            target = copy / PurePosixPath(*src.parts[1:])
            try:
                st = target.stat()
                if st.st_size == size and abs(st.st_mtime - stamp) < 1e-3:
                    continue
            except FileNotFoundError:
                pass
            if target not in stamps:  # one object named twice (``scans`` and ``scans/stamps.csv``) is fetched once
                pairs.append((src, target))
                stamps[target] = stamp
    try:
        store.download_files(pairs)
    except FileNotFoundError as exc:
        raise DatasetIOError(f"{uri}: an object the drive file names vanished while it was fetched ({exc})") from exc
    for target, stamp in stamps.items():
        os.utime(target, (time.time(), stamp))
    storage.atomic_write_bytes(local_yaml, raw)
    return local_yaml


def stage_drive(root: "str | storage.Store", drive_yaml: Path) -> str:
    """Upload a local drive into the object-store root ``root`` once (``ROOT/drives/<fp16>/``, by its drive
    fingerprint) and return the URI of its staged ``drive.yaml``. The drive file and every file or folder it names
    keep their places relative to each other (the common folder of them all is the staged folder); the marker is
    written last, so a drive whose marker is there is complete and is not uploaded again (its marker is rewritten:
    ``cornermap gc`` dates a staged drive by it). Staging holds the root's lock shared, so that ``gc --apply`` (which
    holds it exclusive) never removes a drive while it is staged or found (RunLockedError, exit 75, meanwhile)."""
    from pipeline.fingerprint import drive_fingerprint

    store = storage.Store.open(root)
    drive_yaml = Path(os.path.abspath(drive_yaml))
    key = (store.uri, str(drive_yaml))
    if key in _STAGED:
        return _STAGED[key]
    from pipeline.locks import ROOT_KEY, locks_for

    fp = drive_fingerprint(drive_yaml)
    with locks_for(store).hold(ROOT_KEY, exclusive=False, what=f"stage drive {drive_yaml}"):  # gc waits
        _STAGED[key] = _stage(store, drive_yaml, fp)
    return _STAGED[key]


def _stage(store: storage.Store, drive_yaml: Path, fp: str) -> str:
    from pipeline.fingerprint import _referenced_paths

    sdir = storage.staged_drive_dir(store.root, fp)
    marker = storage.staged_marker(sdir)
    try:
        raw_marker = store.read_bytes(marker)
        doc = json.loads(raw_marker)
        store.put_bytes(marker, raw_marker)  # its time renewed: gc keeps a drive staged less than --min-age-h ago
        return store.url(sdir / doc["drive_file"])
    except (FileNotFoundError, ValueError, KeyError):
        pass
    raw = drive_yaml.read_bytes()
    refs = _referenced_paths(_load(raw, str(drive_yaml)), drive_yaml.parent)
    files = [drive_yaml]
    for path in refs.values():
        path = Path(os.path.normpath(path))
        files.extend(sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path])
    top = Path(
        os.path.commonpath([str(drive_yaml.parent)] + [str(Path(os.path.normpath(p)).parent) for p in refs.values()])
    )
    rels = sorted({Path(os.path.normpath(f)).relative_to(top).as_posix() for f in files})
    store.upload_files([(top / rel, sdir / rel) for rel in rels])
    rel_yaml = drive_yaml.relative_to(top).as_posix()
    doc = {"drive_file": rel_yaml, "fingerprint": fp, "source": str(drive_yaml), "files": rels}
    store.create(marker, json.dumps(doc, indent=1, sort_keys=True).encode("utf-8"))
    return store.url(sdir / rel_yaml)


CHECK_FILE_MAX_BYTES = 16 * 2**20  # a check copy fetches a drive's files up to this size (larger: the name only)
CHECK_MANY_FILES = 16  # a folder's files of one suffix beyond this many (scans) are copied by name only


def preflight_path(drive: "str | Path", scratch: Path | None = None) -> Path | None:
    """The local drive file a client-side check (a stage's ``preflight``) may read for a drive of the plan: a local
    path as is; a URI this process staged, or fetched from an inbox, by its local file; any other URI its check copy
    made in ``scratch`` (``check_copy``; None without ``scratch``)."""
    if not is_uri(drive):
        return Path(drive)
    uri = storage.normalise_uri(drive)
    for (_, local), staged in _STAGED.items():
        if staged == uri:
            return Path(local)
    for local, source in _COPIES.items():
        if source == uri:
            return Path(local)
    if scratch is None:
        return None
    return check_copy(uri, scratch / hashlib.sha256(uri.encode()).hexdigest()[:16])


def check_copy(uri: str, folder: Path) -> Path:
    """What a client-side check of a drive named only by URI reads, copied into ``folder`` without the drive's bulk:
    the drive file, and every object it names in its places relative to the drive file, fetched when at most
    ``CHECK_FILE_MAX_BYTES`` and not one of a folder's many files of one suffix (more than ``CHECK_MANY_FILES``: the
    scans), which are empty files of their names (a check lists them; it does not read them). Returns the local
    ``drive.yaml``; ConfigError naming the URI when the drive file is absent, DatasetIOError when an object
    vanished while it was fetched. The build's tasks fetch the drive whole (``local_drive``), as before."""
    from collections import Counter

    store, loc, raw = _read_drive_yaml(uri)
    fetch: dict[Path, PurePosixPath] = {}
    names: set[Path] = set()
    for value, objects in _referenced(store, loc, raw).items():
        base = PurePosixPath(posixpath.normpath(posixpath.join(loc.parent.as_posix(), value)))
        kinds = Counter(PurePosixPath(rel).suffix.lower() for rel in objects if rel)
        for rel, (size, _, _) in objects.items():
            src = base / rel if rel else base
            target = storage.inside(folder, *src.parts[1:])
            if (rel and kinds[PurePosixPath(rel).suffix.lower()] > CHECK_MANY_FILES) or size > CHECK_FILE_MAX_BYTES:
                names.add(target)
            else:
                fetch[target] = src
    for target in sorted(names - set(fetch)):
        target.parent.mkdir(parents=True, exist_ok=True)
        target.touch()
    try:
        store.download_files([(src, target) for target, src in fetch.items()])
    except FileNotFoundError as exc:
        raise DatasetIOError(f"{uri}: an object the drive file names vanished while it was fetched ({exc})") from exc
    local_yaml = storage.inside(folder, *loc.parts[1:])
    storage.atomic_write_bytes(local_yaml, raw)
    return local_yaml


_COPIES: dict[str, str] = {}  # local copy of a delivered drive.yaml -> its s3:// URI, this process


def remember_copy(drive_yaml: "str | Path", uri: str) -> None:
    """This process's local copy ``drive_yaml`` of a drive fetched from an object store stands for ``uri``."""
    _COPIES[os.path.abspath(drive_yaml)] = uri


def source_of_copy(drive_yaml: "str | Path") -> str | None:
    """The ``s3://`` URI of a drive file this process fetched from an object-store inbox into its local copy
    (``mapservice.inbox.StoreInbox.fetch``), None for any other path: a build names the drive by it, so that its
    tasks read the drive from the bucket, never from this process's copy."""
    return _COPIES.get(os.path.abspath(drive_yaml))
