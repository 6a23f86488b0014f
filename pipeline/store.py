"""The Parquet store: schema-validated, atomic writes; manifests as commit markers; readers see committed data.

The layout under the output root is ``pipeline.storage``'s (the one module that spells it): a dataset's
``_manifest.json`` is written last and is its commit marker; ``_parts/<label>.json`` are per-partition commit
markers (resume after a kill); ``data/drive=../chunk=../part-<label>-<seq>.parquet`` the tables;
``artifacts/<label>/`` a partition's non-tabular files.

Verified reads: a stage reading a dataset first checks each Parquet file's sha256 against the dataset
manifest (and each artifact file's, for manifests that record it); a mismatch is an ``IntegrityError``.
A file verified once is not hashed again by the same process while its size, mtime and inode are unchanged, nor
by another process of the same run when the run has a verification ledger (``verify_file``; ~1.9 GB/s of sha256
on the 2-core machine). Every path from a manifest or a partition value is resolved
inside the dataset directory (``PathEscapeError`` otherwise). Reading is ``pipeline.reader``.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import threading
import time
import uuid
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path, PurePosixPath
from typing import Any, Iterable, Iterator

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pipeline import storage
from pipeline.errors import DatasetIOError, IntegrityError, SchemaMismatchError
from pipeline.fingerprint import file_sha256
from pipeline.names import inside
from pipeline.storage import FP_LEN  # noqa: F401 - re-exported

_VERIFIED: dict[tuple[str, int, int, int], str] = {}  # (path, size, mtime_ns, inode) -> sha256, this process
_VERIFIED_LOCK = threading.Lock()


def _ledger_entry(ledger: Path, key: tuple[str, int, int, int], sha256: str) -> Path:
    import hashlib

    return ledger / hashlib.sha256("\0".join(map(str, (*key, sha256))).encode()).hexdigest()[:32]


def _file_key(path: Path, st: os.stat_result) -> tuple[str, int, int, int]:
    return (str(path), st.st_size, st.st_mtime_ns, st.st_ino)


def verify_file(path: Path, sha256: str | None, dataset: str, ledger: Path | None = None) -> None:
    """Raise IntegrityError unless ``path``'s sha256 is ``sha256`` (None: nothing recorded, not checked).

    A file is hashed once per process while its size, mtime and inode are unchanged; with a run's ``ledger`` (a
    folder the engine makes for one run, ``pipeline.flow``) once per run: the process that wrote it during the run
    (``record_verified``) or the first that verified it leaves an entry there, and every other process of the run
    trusts that entry (measured with py-spy on a demo build: each of the 4 processes hashed the 2.3 GB of scans it
    read, 14 CPU s of the build)."""
    if sha256 is None:
        return
    try:
        st = os.stat(path)
    except OSError as exc:
        raise DatasetIOError(f"{path} (dataset {dataset!r}): listed in its manifest but unreadable "
                             f"({exc.strerror or exc}); hint: delete the dataset directory to rebuild it") from exc
    key = _file_key(path, st)
    if _VERIFIED.get(key) == sha256:
        return
    entry = _ledger_entry(ledger, key, sha256) if ledger is not None else None
    if entry is None or not entry.exists():
        got = file_sha256(path)
        if got != sha256:
            raise IntegrityError(f"{path} (dataset {dataset!r}): sha256 {got[:16]}... differs from its manifest's "
                                 f"{sha256[:16]}...; the file is corrupt or was altered. hint: delete the dataset "
                                 "directory (its fingerprint folder) to rebuild it")
        _mark(entry)
    with _VERIFIED_LOCK:
        _VERIFIED[key] = sha256


def record_verified(path: Path, sha256: str, ledger: Path | None) -> None:
    """``path`` (just written and hashed to ``sha256`` by this process) needs no verification for the rest of the run:
    entered in this process's cache and in the run's ``ledger`` (see ``verify_file``)."""
    key = _file_key(path, os.stat(path))
    with _VERIFIED_LOCK:
        _VERIFIED[key] = sha256
    if ledger is not None:
        _mark(_ledger_entry(ledger, key, sha256))


def _mark(entry: Path | None) -> None:
    """Create a ledger entry (an empty file; the ledger folder is made at the first entry). A ledger that cannot be
    written (a read-only root) only means other processes hash the file again."""
    if entry is None:
        return
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        entry.touch()
    except OSError:
        pass


def dataset_dir(root: Path, dataset: str, fingerprint: str) -> Path:
    return storage.dataset_dir(Path(root), dataset, fingerprint)


def atomic_write_text(path: Path, text: str) -> None:
    storage.atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1, sort_keys=True, default=str))


def conform_table(table: pa.Table, schema: pa.Schema, where: str) -> pa.Table:
    """Check a table against its schema; numeric types are cast safely, everything else must match.

    Raises SchemaMismatchError listing every bad column with expected vs actual type.
    """
    problems: list[str] = []
    got = {f.name: f.type for f in table.schema}
    for f in schema:
        if f.name not in got:
            problems.append(f"missing column {f.name!r} (expected {f.type})")
        elif got[f.name] != f.type:
            a, b = got[f.name], f.type
            numeric = lambda t: pa.types.is_integer(t) or pa.types.is_floating(t)  # noqa: E731
            castable = (numeric(a) and numeric(b)) or (pa.types.is_list(a) and pa.types.is_list(b)) or \
                pa.types.is_null(a) or (pa.types.is_large_string(a) and pa.types.is_string(b))
            if not castable:
                problems.append(f"column {f.name!r}: expected {b}, got {a}")
    for name in got:
        if name not in schema.names:
            problems.append(f"unexpected column {name!r} ({got[name]}); the schema has {schema.names}")
    if problems:
        raise SchemaMismatchError(f"{where}: {len(problems)} bad column(s):\n  - " + "\n  - ".join(problems) +
                                  "\n  hint: fix the stage's compute or the schema in schemas/")
    try:
        table = table.select(schema.names).cast(schema, safe=True)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise SchemaMismatchError(f"{where}: values do not fit the schema's types: {exc}") from exc
    nulls = [f.name for f in schema if not f.nullable and table[f.name].null_count]
    if nulls:
        raise SchemaMismatchError(f"{where}: nulls in non-nullable column(s) {nulls}")
    return table


ROW_GROUP_KEY = b"row_group_key"  # schema metadata: the column whose runs the row groups follow
ROW_GROUP_MIN_ROWS = 32_768  # a row group ends at a run boundary once it holds at least this many rows
ROW_GROUP_MAX_ROWS = 1_048_576  # and never holds more (pyarrow's default row group size)


def row_group_bounds(keys, min_rows: int | None = None, max_rows: int | None = None) -> list[int]:
    """Row offsets where the row groups of a table start (and the row count at the end): each group ends where
    the key changes, after at least ``min_rows`` rows, so that a reader looking for a few keys (``read_in``)
    decodes those keys' rows and little else; a run longer than ``max_rows`` is cut into groups of that size.
    Measured on demo scans_raw (~50k points per scan): one scan read decoded a 1,048,576-row group in 34 ms
    before, its own group in 1.9 ms with key-aligned groups; a whole-file read is unchanged."""
    import numpy as np

    min_rows = ROW_GROUP_MIN_ROWS if min_rows is None else min_rows
    max_rows = ROW_GROUP_MAX_ROWS if max_rows is None else max_rows
    keys = np.asarray(keys)
    n = len(keys)
    runs = np.r_[0, np.flatnonzero(keys[1:] != keys[:-1]) + 1, n]
    bounds, start = [0], 0
    for end in runs[1:]:
        while end - start > max_rows:
            start += max_rows
            bounds.append(start)
        if end - start >= min_rows or end == n:
            bounds.append(int(end))
            start = int(end)
    return bounds


# Intermediates are written once and read several times (a scans_raw file: by the odometry, twice by the corners,
# scattered by the pose graph). LZ4 against zstd on a gangnam scans_raw file (1.97 M points, 41
# row groups): written in 0.102 s instead of 0.136 s, its odometry columns read in 0.018 s instead of 0.035-0.039 s,
# 24.0 MB instead of 22.2 MB. Files written before keep their codec (a reader takes either).
COMPRESSION = "lz4"
WRITE_THREADS = 2  # files of one output written at a time (write_pieces)


def _encodings(schema: pa.Schema) -> dict[str, Any]:
    """Dictionary encoding for the string columns (drive names, reasons), byte-stream-split for the floating-point
    ones (a dictionary of coordinates overflows and falls back to plain after the try), plain for the integers
    (ids, stamps, rings: LZ4 takes their runs). Measured on a demo scans_raw file (1.95 M points): 30.3 -> 22.5 MB
    with zstd, written in 137 ms, not 258 (the store now writes LZ4: ``COMPRESSION``); on 12 demo scans_raw files
    (18.6 M points) with LZ4, the integers' dictionaries cost 0.956 against 0.808 CPU s to write, for 231.1 against
    232.5 MB."""
    floats = [f.name for f in schema if pa.types.is_floating(f.type)]
    strings = [f.name for f in schema if pa.types.is_string(f.type) or pa.types.is_large_string(f.type)
               or pa.types.is_dictionary(f.type)]
    return {"use_dictionary": strings or False, "use_byte_stream_split": floats or False}


def write_parquet_atomic(table: pa.Table, path: Path) -> dict[str, Any]:
    """Write ``table`` to ``path`` (a temporary file renamed into place). When the schema's metadata names a
    ``row_group_key`` column, the row groups follow that column's runs (``row_group_bounds``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    key = (table.schema.metadata or {}).get(ROW_GROUP_KEY)
    try:
        with pq.ParquetWriter(tmp, table.schema, compression=COMPRESSION, **_encodings(table.schema)) as writer:
            if key is not None and key.decode() in table.column_names and table.num_rows:
                bounds = row_group_bounds(table[key.decode()].to_numpy())
                for a, b in zip(bounds[:-1], bounds[1:]):
                    writer.write_table(table.slice(a, b - a), row_group_size=b - a)
            else:
                writer.write_table(table)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise DatasetIOError(f"cannot write {path}: {exc}") from exc
    return {"rows": table.num_rows, "bytes": path.stat().st_size, "sha256": file_sha256(path)}


def _split_by_partition(table: pa.Table, partitioning: tuple[str, ...]) -> list[tuple[str, dict[str, Any], pa.Table]]:
    """Split a piece into one table per value combination of the partition columns (hive sub-directories)."""

    if not partitioning:
        return [("", {}, table)]
    combos = table.select(list(partitioning)).group_by(list(partitioning)).aggregate([]).to_pylist()
    out = []
    for combo in sorted(combos, key=lambda c: tuple(str(v) for v in c.values())):
        sub = table
        if len(combos) > 1:
            mask = None
            for k, v in combo.items():
                m = pc.equal(table[k], v)
                mask = m if mask is None else pc.and_(mask, m)
            sub = table.filter(mask)
        out.append(("/".join(f"{k}={v}" for k, v in combo.items()), combo, sub))
    return out


def prefetched(pieces: Iterable[Any], depth: int = 1) -> Iterator[Any]:
    """``pieces`` in order, the next ones (at most ``depth`` waiting) produced in a background thread while the caller
    works on this one: a stage that streams its output (ingest decoding scan files) computes the next piece while
    the store compresses and writes the last (both release the GIL for most of their time). An exception of the
    producer is raised here, at the piece it failed on; when the caller stops early the producer stops after its
    current piece and its generator is closed. Measured on gangnam drive_0 (9,554 scans): decoding 28.6 s and writing
    42.9 s one after the other."""
    import queue

    q: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()
    end = object()

    def put(entry) -> bool:
        while not stop.is_set():
            try:
                q.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        it = iter(pieces)
        try:
            for item in it:
                if not put((True, item)):
                    break
            else:
                put((True, end))
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put((False, exc))
        finally:
            if stop.is_set() and hasattr(it, "close"):
                it.close()

    thread = threading.Thread(target=produce, name="prefetch-pieces", daemon=True)
    thread.start()
    try:
        while True:
            ok, item = q.get()
            if not ok:
                raise item
            if item is end:
                return
            yield item
    finally:
        stop.set()
        thread.join()


def write_pieces(pieces: Iterable[pa.Table] | pa.Table | None, *, out_dir: Path, label: str,
                 schema: pa.Schema, partitioning: tuple[str, ...], where: str,
                 ledger: Path | None = None) -> list[dict[str, Any]]:
    """Write one output of one partition task; returns the file records for its part manifest, in the pieces'
    order. A streamed output (an iterator of tables) is produced one piece ahead of the writes (``prefetched``),
    which ``WRITE_THREADS`` threads do. Each file written is entered in the run's ``ledger`` as verified
    (``record_verified``)."""
    for stale in storage.data_dir(Path(out_dir)).glob(f"**/part-{label}-*.parquet"):
        stale.unlink()  # left by a killed attempt; never listed in a manifest
    if pieces is None:
        return []
    if isinstance(pieces, pa.Table):
        pieces = [pieces]
    elif not isinstance(pieces, (list, tuple)):
        pieces = prefetched(pieces)
    records: list[dict[str, Any]] = []
    seq = 0

    def write(piece: pa.Table, path: Path, parts: dict[str, Any]) -> dict[str, Any]:
        rec = write_parquet_atomic(piece, path)
        record_verified(path, rec["sha256"], ledger)
        rec.update(path=str(path.relative_to(Path(out_dir).resolve())), partition=parts)
        return rec

    # the files of a stream are encoded, compressed and hashed by WRITE_THREADS threads (pyarrow and hashlib release
    # the GIL): one writer was the ingest's bottleneck (gangnam: 2.9 ms a scan of its 4 ms); at most that many pieces
    # wait or are written at a time, and the records keep the pieces' order
    with ThreadPoolExecutor(max_workers=WRITE_THREADS, thread_name_prefix="write-pieces") as pool:
        in_flight: deque = deque()
        for table in pieces:
            if table is None:
                continue
            table = conform_table(table, schema, where)
            if table.num_rows == 0:
                continue
            for sub, parts, piece in _split_by_partition(table, partitioning):
                path = inside(storage.data_dir(Path(out_dir)), sub, f"part-{label}-{seq:05d}.parquet")
                seq += 1
                if len(in_flight) >= WRITE_THREADS:
                    records.append(in_flight.popleft().result())
                in_flight.append(pool.submit(write, piece, path, parts))
        while in_flight:
            records.append(in_flight.popleft().result())
    return records


def read_manifest(out_dir: Path) -> dict[str, Any] | None:
    path = storage.dataset_manifest(Path(out_dir))
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetIOError(f"{path}: unreadable manifest ({exc}); delete the directory to rebuild") from exc


def commit_artifacts(staging: Path, final: Path) -> list[dict[str, Any]]:
    """Move a partition's staged artifact directory into place; returns (path, bytes, sha256) records."""
    if not staging.exists():
        return []
    if final.exists():
        shutil.rmtree(final)  # a killed attempt's leftovers; never listed in a manifest
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(staging, final)
    return [{"path": str(p.relative_to(final)), "bytes": p.stat().st_size, "sha256": file_sha256(p)}
            for p in sorted(final.rglob("*")) if p.is_file()]


class DataRoot:
    """The committed datasets of one output root as the engine reads and writes them (``pipeline.execute``,
    ``pipeline.reader``, ``pipeline.flow``).

    A local root is itself: files are read and written in place. An object-store root (``s3://bucket/prefix``) has
    a *local copy* in this process's scratch (``storage.mirror_dir``: a dask worker's ``--local-directory``): a task
    fetches the files it reads into it (``fetch``; each is then sha256-verified as on a local root), writes its
    outputs there, uploads them (``upload``), then its part marker (``put_part``); the stage's manifest is created
    last, with a conditional put (``commit``). Manifests and part markers are always read from the store, never
    from the copy: the store alone says what is committed."""

    def __init__(self, uri: "str | Path | storage.Store"):
        self.store = storage.Store.open(uri)
        self.uri = self.store.uri
        self.remote = not self.store.local
        self.local = storage.mirror_dir(self.uri) if self.remote else Path(self.store.root)
        if self.remote:
            use_local_copy(self.local)

    def __repr__(self) -> str:
        return f"DataRoot({self.uri!r})"

    def dir(self, dataset: str, fingerprint: str) -> Path:
        """The dataset's local directory (on an object-store root: its local copy)."""
        return storage.dataset_dir(self.local, dataset, fingerprint)

    def loc(self, dataset: str, fingerprint: str):
        """The dataset's location on the store."""
        return storage.dataset_dir(self.store.root, dataset, fingerprint)

    def where(self, dataset: str, fingerprint: str) -> str:
        return self.store.url(self.loc(dataset, fingerprint))

    def _json(self, loc) -> dict[str, Any] | None:
        try:
            raw = self.store.read_bytes(loc)
        except FileNotFoundError:
            return None
        try:
            return json.loads(raw)
        except ValueError as exc:
            raise DatasetIOError(f"{self.store.url(loc)}: unreadable JSON ({exc}); delete the dataset directory to "
                                 "rebuild") from exc

    def manifest(self, dataset: str, fingerprint: str) -> dict[str, Any] | None:
        """The dataset's committed manifest, None when it is not committed."""
        if not self.remote:
            return read_manifest(self.dir(dataset, fingerprint))
        return self._json(storage.dataset_manifest(self.loc(dataset, fingerprint)))

    def part(self, dataset: str, fingerprint: str, label: str) -> dict[str, Any] | None:
        """Partition ``label``'s part marker (its commit record), None when absent or unreadable."""
        if not self.remote:
            try:
                return json.loads(storage.part_marker(self.dir(dataset, fingerprint), label).read_text())
            except (OSError, ValueError):
                return None
        try:
            return self._json(storage.part_marker(self.loc(dataset, fingerprint), label))
        except DatasetIOError:
            return None

    def put_part(self, dataset: str, fingerprint: str, label: str, doc: dict[str, Any]) -> None:
        """Write partition ``label``'s part marker (after its files are in place)."""
        raw = json.dumps(doc, indent=1, sort_keys=True, default=str).encode("utf-8")
        if not self.remote:
            storage.atomic_write_bytes(storage.part_marker(self.dir(dataset, fingerprint), label), raw)
        else:
            self.store.put_bytes(storage.part_marker(self.loc(dataset, fingerprint), label), raw)

    def commit(self, dataset: str, fingerprint: str, manifest: dict[str, Any]) -> bool:
        """Write the dataset's manifest, its commit marker, last. On an object store a conditional put: False when
        another writer committed the same fingerprint first (its manifest stays; the data are the same stage's on
        the same inputs)."""
        if not self.remote:
            atomic_write_json(storage.dataset_manifest(self.dir(dataset, fingerprint)), manifest)
            return True
        raw = json.dumps(manifest, indent=1, sort_keys=True, default=str).encode("utf-8")
        return self.store.create(storage.dataset_manifest(self.loc(dataset, fingerprint)), raw)

    def fetch(self, dataset: str, fingerprint: str, records: Iterable[tuple[str, int | None]],
              force: bool = False) -> None:
        """Make the dataset's files ``records`` ((path relative to the dataset directory, bytes)) present in the
        local copy: those absent or of another size are downloaded (whole, renamed into place). A local root holds
        them already."""
        if not self.remote:
            return
        base = self.dir(dataset, fingerprint)
        pairs = []
        for rel, size in records:
            target = inside(base, rel)
            if not force:
                try:
                    st = target.stat()
                    if size is None or st.st_size == int(size):
                        _touch(target, st)  # read now: the last to go when the copies are pruned
                        continue
                except FileNotFoundError:
                    pass
            pairs.append((self.loc(dataset, fingerprint) / PurePosixPath(rel).as_posix(), target))
        if pairs:
            try:
                self.store.download_files(pairs)
            except FileNotFoundError as exc:
                raise DatasetIOError(f"{self.where(dataset, fingerprint)}: a file listed in its manifest is missing "
                                     f"from the store ({exc}); hint: delete the dataset directory to rebuild it") \
                    from exc

    def upload(self, dataset: str, fingerprint: str, rels: Iterable[str]) -> None:
        """Upload the local copy's files ``rels`` (relative to the dataset directory) to the store."""
        if not self.remote:
            return
        base, loc = self.dir(dataset, fingerprint), self.loc(dataset, fingerprint)
        self.store.upload_files([(inside(base, rel), loc / PurePosixPath(rel).as_posix()) for rel in rels])

    def siblings(self, dataset: str) -> list[str]:
        """The fingerprint folders of ``dataset`` on the store."""
        return self.store.listdir(storage.datasets_dir(self.store.root) / dataset)


_DATA_ROOTS: dict[str, DataRoot] = {}

# --- the local copies, bounded ---------------------------------------------------------------------------------------
# The local copies of object-store roots and inboxes (``storage.local_copy_bases``: ``cornermap-cache/`` and
# ``cornermap-drives/`` in the scratch folder) are a cache: an LRU with a size cap. A process using a copy holds a
# shared flock on ``<copy>.inuse`` for its life; when a command ends (the process that is no one's child: not a
# pool process, not a dask worker), it prunes the copies no running process uses, least recently read file first
# (``fetch`` sets a file's access time when it is read again), until they hold at most ``CORNERMAP_CACHE_GIB``
# (default 10; 0: every idle copy is removed at the end of each command). A command killed with SIGKILL prunes
# nothing; the next one that ends does.
_IN_USE: dict[Path, int] = {}  # copy folder -> the fd of its shared flock, this process
_PRUNE_AT_EXIT: list[bool] = []


def _touch(path: Path, st: os.stat_result) -> None:
    try:
        os.utime(path, ns=(time.time_ns(), st.st_mtime_ns))
    except OSError:
        pass


def _inuse_file(copy: Path) -> Path:
    return copy.with_name(copy.name + ".inuse")


def use_local_copy(copy: Path) -> None:
    """Mark the local copy folder ``copy`` as used by this process (a shared flock, released when it exits) and, in a
    command's own process, prune the idle copies when it ends (``prune_local_copies``)."""
    import atexit
    import fcntl
    import multiprocessing

    copy = Path(copy)
    if copy in _IN_USE:
        return
    copy.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(_inuse_file(copy), os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_SH)  # waits while a pruner removes this copy (exclusive, short)
    _IN_USE[copy] = fd
    if not _PRUNE_AT_EXIT and multiprocessing.parent_process() is None and not _in_dask_worker():
        _PRUNE_AT_EXIT.append(True)
        atexit.register(_prune_at_exit)


def _in_dask_worker() -> bool:
    if "distributed" not in sys.modules:
        return False
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError, AttributeError):
        return False


def cache_cap_bytes() -> float:
    try:
        gib = float(os.environ.get(storage.CACHE_GIB_ENV, storage.DEFAULT_CACHE_GIB))
    except ValueError:
        gib = storage.DEFAULT_CACHE_GIB
    return max(gib, 0.0) * 2**30


def _prune_at_exit() -> None:
    for copy in list(_IN_USE):
        os.close(_IN_USE.pop(copy))
    try:
        prune_local_copies()
    except OSError as exc:  # a cache: never fail a command's exit over it
        logging.getLogger(__name__).warning("pruning the local copies failed: %s", exc)


def prune_local_copies(cap_bytes: float | None = None) -> tuple[int, int]:
    """Remove files of the local copies no running process uses, least recently read first, until all copies hold
    at most ``cap_bytes`` (default ``cache_cap_bytes()``); a copy left empty is removed whole. Returns (files removed,
    bytes left)."""
    import fcntl

    cap = cache_cap_bytes() if cap_bytes is None else cap_bytes
    held: list[int] = []
    files: list[tuple[float, int, Path]] = []
    busy_bytes = 0
    idle: list[Path] = []
    try:
        for base in storage.local_copy_bases():
            if not base.is_dir():
                continue
            for copy in sorted(p for p in base.iterdir() if p.is_dir()):
                fd = os.open(_inuse_file(copy), os.O_RDWR | os.O_CREAT, 0o644)
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    os.close(fd)
                    busy_bytes += sum(p.stat().st_size for p in copy.rglob("*") if p.is_file())
                    continue
                held.append(fd)
                idle.append(copy)
                for p in copy.rglob("*"):
                    if p.is_file() and not p.is_symlink():
                        st = p.stat()
                        files.append((st.st_atime, st.st_size, p))
        total = busy_bytes + sum(size for _, size, _ in files)
        removed = 0
        for _, size, p in sorted(files, key=lambda f: f[0]):
            if total <= cap:
                break
            p.unlink(missing_ok=True)
            total -= size
            removed += 1
        for copy in idle:
            if removed and not any(p.is_file() for p in copy.rglob("*")):
                shutil.rmtree(copy, ignore_errors=True)
        return removed, int(total)
    finally:
        for fd in held:
            os.close(fd)


def data_root(uri: "str | Path | DataRoot") -> DataRoot:
    """The ``DataRoot`` of ``uri`` (one per root and process)."""
    if isinstance(uri, DataRoot):
        return uri
    key = str(uri)
    root = _DATA_ROOTS.get(key)
    if root is None:
        root = _DATA_ROOTS[key] = DataRoot(uri)
    return root
