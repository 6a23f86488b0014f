"""The store of one output root: the only module that spells its layout, on a local folder or on S3.

A root is named by ``--root``: a local folder (``runs/city``, as always) or an object-store URI
(``s3://bucket/prefix``). ``Store.open(uri)`` gives its one face; the layout functions below give the location of
every object of a root, for a local ``Path`` root and for the ``PurePosixPath`` ``bucket/prefix`` of an S3 one alike::

    datasets/<dataset>/<fp16>/_manifest.json      the dataset's commit marker, written last
    datasets/<dataset>/<fp16>/_parts/<label>.json a partition's commit marker
    datasets/<dataset>/<fp16>/data/...            Parquet files (hive partitions)
    datasets/<dataset>/<fp16>/artifacts/<label>/  a partition's non-tabular files
    maps/<name>/LATEST                            "vNNNN <sha256 of its manifest.json>", replaced atomically
    maps/<name>/vNNNN/manifest.json               a version's commit marker, written last
    maps/<name>/map.json                          the map's identity
    maps/<name>/gate/vNNNN.json                   the regression gate's comparison of candidate vNNNN
    locks/<key>.lock                              locks (local: flock; S3: lease objects, ``pipeline.leases``)
    tmp/                                          scratch of runs (ledgers, logs, staging)
    workflows/build-<map>-<sha8>.yaml             the workflows `cornermap build` wrote
    drives/<fp16>/...                             local drives a build on an object-store root staged into it
    drives/<fp16>/_staged.json                    the staged drive's commit marker, written last

Backends: a local folder is plain ``pathlib``/``os`` (the engine's hot paths are unchanged); S3 is ``s3fs`` (fsspec),
chosen over ``pyarrow.fs`` by measurement (docs/storage.md, ``bench/bench_store.py --backends``: 100 small PUTs
0.74 s against 1.39 s, a 64 MB GET 0.35 s against 13.8 s on the local moto server), and because s3fs offers the
conditional put ``If-None-Match`` that commit markers and lock objects need. Endpoint and credentials come from the
standard AWS environment (``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, ``AWS_PROFILE``),
so MinIO, Ceph and cloud buckets work alike.

Object-store semantics (``docs/storage.md``): an S3 object appears whole or not at all; a commit marker
(``_manifest.json``, a version's ``manifest.json``) is written after every file it lists, with ``If-None-Match: *``
so that two writers never both commit; ``LATEST`` is one PUT (atomic replace); locks are lease objects with an
expiry (``pipeline.leases``).
"""
from __future__ import annotations

import hashlib
import os
import re
import sys
import uuid
from pathlib import Path, PurePath, PurePosixPath
from typing import Iterator, TypeVar

# --- the layout, stated once ---------------------------------------------------------------------------------------
DATASETS = "datasets"
DATASET_MANIFEST = "_manifest.json"
PARTS = "_parts"
DATA = "data"
ARTIFACTS = "artifacts"
MAPS = "maps"
LATEST = "LATEST"
VERSION_MANIFEST = "manifest.json"
IDENTITY = "map.json"
PUBLISH_LOCK = ".publish.lock"  # a local collection's flock file (pipeline.versioned)
GATE = "gate"
LOCKS = "locks"
TMP = "tmp"
WORKFLOWS = "workflows"  # the build workflows `cornermap build` writes (one per map and drive set)
DRIVES = "drives"  # local drives staged into an object-store root (pipeline.drive_store), by content
STAGED_MARKER = "_staged.json"
FP_LEN = 16
VERSION_RE = re.compile(r"^v(\d{4,})$")

P = TypeVar("P", bound=PurePath)


def version_name(version: int) -> str:
    """``3`` -> ``"v0003"``: the name of a version directory."""
    return f"v{int(version):04d}"


def datasets_dir(root: P) -> P:
    return root / DATASETS


def dataset_dir(root: P, dataset: str, fingerprint: str) -> P:
    """The directory of one committed (or committing) dataset: ``datasets/<dataset>/<fp16>``."""
    return root / DATASETS / dataset / fingerprint[:FP_LEN]


def dataset_manifest(ddir: P) -> P:
    return ddir / DATASET_MANIFEST


def part_marker(ddir: P, label: str) -> P:
    return ddir / PARTS / f"{label}.json"


def parts_dir(ddir: P) -> P:
    return ddir / PARTS


def data_dir(ddir: P) -> P:
    return ddir / DATA


def artifacts_dir(ddir: P, label: str | None = None) -> P:
    return ddir / ARTIFACTS if label is None else ddir / ARTIFACTS / label


def maps_dir(root: P) -> P:
    return root / MAPS


def map_dir(root: P, name: str) -> P:
    return root / MAPS / name


def root_of_map(mdir: P) -> P:
    """The output root of ``ROOT/maps/NAME``."""
    return mdir.parent.parent


def latest_file(mdir: P) -> P:
    return mdir / LATEST


def version_dir(mdir: P, version: int) -> P:
    return mdir / version_name(version)


def version_manifest(vdir: P) -> P:
    return vdir / VERSION_MANIFEST


def identity_file(mdir: P) -> P:
    return mdir / IDENTITY


def gate_dir(mdir: P) -> P:
    return mdir / GATE


def gate_file(mdir: P, version: int) -> P:
    return mdir / GATE / f"{version_name(version)}.json"


def locks_dir(root: P) -> P:
    return root / LOCKS


def tmp_dir(root: P, *parts: str) -> P:
    return root.joinpath(TMP, *parts)


def workflows_dir(root: P) -> P:
    return root / WORKFLOWS


def drives_dir(root: P) -> P:
    """The drives staged into a root (``drives/``), one folder each."""
    return root / DRIVES


def staged_drive_dir(root: P, fingerprint: str) -> P:
    """Where a local drive staged into an object-store root lives: ``drives/<fp16>`` (its drive fingerprint)."""
    return drives_dir(root) / fingerprint[:FP_LEN]


def staged_drive_of(value: object, root: "Path | str") -> str | None:
    """The ``fp16`` of the staged drive ``ROOT/drives/<fp16>/`` that a drive path or URI ``value`` lies in (``root``
    a local folder or an ``s3://`` URI); None when it lies elsewhere."""
    if not isinstance(value, (str, PurePath)) or not str(value):
        return None
    if uri_scheme(root) is not None:
        if uri_scheme(value) is None:
            return None
        base, text = normalise_uri(root).rstrip("/") + f"/{DRIVES}/", normalise_uri(value)
        rest = text[len(base):] if text.startswith(base) else None
    else:
        if uri_scheme(value) is not None:
            return None
        try:
            rest = Path(os.path.abspath(value)).relative_to(Path(os.path.abspath(root)) / DRIVES).as_posix()
        except ValueError:
            rest = None
    fp = rest.split("/", 1)[0] if rest else ""
    return fp if len(fp) == FP_LEN else None


def staged_marker(sdir: P) -> P:
    return sdir / STAGED_MARKER


SCRATCH_ENV = "CORNERMAP_SCRATCH"  # a process's local scratch folder (default: a dask worker's, else the system's)
CACHE = "cornermap-cache"  # under the scratch: local copies of object-store roots, one folder per root URI
DRIVE_CACHE = "cornermap-drives"  # under the scratch: local copies of drives delivered to a bucket, one per inbox URI
CACHE_GIB_ENV = "CORNERMAP_CACHE_GIB"  # the size cap of those local copies (``store.prune_local_copies``)
DEFAULT_CACHE_GIB = 10.0


def scratch_base() -> Path:
    """This process's local scratch folder: ``$CORNERMAP_SCRATCH``, else the dask worker's ``--local-directory``
    when the process is one, else the system's temporary folder."""
    env = os.environ.get(SCRATCH_ENV)
    if env:
        return Path(env)
    if "distributed" in sys.modules:
        try:
            from distributed import get_worker

            return Path(get_worker().local_directory)
        except (ImportError, ValueError, AttributeError):
            pass
    import tempfile

    return Path(tempfile.gettempdir())


def mirror_dir(uri: str) -> Path:
    """The local copy of an object-store root in this process's scratch (the files its tasks read and write): named
    by a hash of the root's URI, never after the URI itself."""
    return scratch_base() / CACHE / hashlib.sha256(normalise_uri(uri).encode()).hexdigest()[:16]


def drive_copy_dir(inbox_uri: str) -> Path:
    """The local copy of an object-store inbox's drives in this process's scratch (what a build reads): named by a
    hash of the inbox's URI."""
    return scratch_base() / DRIVE_CACHE / hashlib.sha256(normalise_uri(inbox_uri).encode()).hexdigest()[:16]


def local_copy_bases() -> list[Path]:
    """The folders of this process's scratch that hold local copies of object-store roots and inboxes."""
    return [scratch_base() / CACHE, scratch_base() / DRIVE_CACHE]


def join_uri(root: object, rel: str) -> "str | Path":
    """``rel`` (a relative path as a dataset row records it) under a root: a ``Path`` for a local root, the object's
    URI for an object-store root."""
    if uri_scheme(root) is None:
        return Path(str(root)) / rel
    return f"{normalise_uri(root)}/{PurePosixPath(rel).as_posix()}"


def is_root_dir(root: Path) -> bool:
    """Whether a local folder looks like an output root (it holds datasets/, maps/ or tmp/)."""
    return any((Path(root) / sub).is_dir() for sub in (DATASETS, MAPS, TMP))


# --- root URIs -----------------------------------------------------------------------------------------------------
_URI_RE = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*):/")  # "s3://b/p", and "s3:/b/p" after pathlib collapsed the "//"
SCHEMES = ("s3",)  # object stores a root may live on


def inside(root: Path | str, *parts: str | Path) -> Path:
    """``root/parts...`` resolved (``..`` and symlinks); PathEscapeError unless it stays under ``root``."""
    from pipeline.errors import PathEscapeError

    base = Path(root).resolve()
    for p in parts:
        if Path(p).is_absolute():
            raise PathEscapeError(f"{p!s}: an absolute path where a path relative to {base} was expected")
    path = base.joinpath(*parts).resolve()
    if path != base and base not in path.parents:
        rel = "/".join(str(p) for p in parts)
        raise PathEscapeError(f"{rel!r} resolves to {path}, outside {base}; hint: paths from input must stay "
                              "inside their root")
    return path


def uri_scheme(value: object) -> str | None:
    """The scheme of a URI (``"s3"`` for ``s3://bucket/prefix``), None for a local path. A ``Path`` made from a URI
    (``Path("s3://b/p")`` is ``s3:/b/p``) is still recognised: it was never meant as a local folder."""
    if value is None:
        return None
    m = _URI_RE.match(str(value))
    if m is None or (len(m.group(1)) == 1 and os.name == "nt"):
        return None
    return m.group(1).lower()


def normalise_uri(value: object) -> str:
    """``s3:/b/p`` (a URI that went through ``pathlib``) or ``s3://b/p/`` -> ``s3://b/p``."""
    scheme = uri_scheme(value)
    if scheme is None:
        return str(value)
    rest = str(value)[len(scheme) + 1:].lstrip("/")
    return f"{scheme}://{rest.rstrip('/')}"


def refuse_uri(value: object, option: str, supported: str = "a local folder") -> None:
    """OptionError (exit 2) naming ``option`` when ``value`` is a URI: a command that does not (yet) read or write
    object storage must never take ``s3://bucket/root`` for the relative folder ``s3:/bucket/root``."""
    scheme = uri_scheme(value)
    if scheme is None:
        return
    from pipeline.errors import OptionError

    hint = ("write to a folder, then `cornermap tiles push --root FOLDER --map NAME --to s3://BUCKET/PREFIX` "
            "publishes its map" if option == "--root" else "copy it to a local folder first")
    raise OptionError(option, [f"{normalise_uri(value)} is an object-store URI ({scheme}://); this command takes "
                               f"{supported} here; hint: {hint} (docs/storage.md)"])


def local_path(value: object, option: str) -> Path:
    """``value`` as a local folder; OptionError (exit 2) for a URI."""
    refuse_uri(value, option)
    return Path(str(value))


TRANSFERS = 4  # files an S3 upload or download moves at a time (Store.upload_files, download_files)


# --- one face over both backends -----------------------------------------------------------------------------------
class Store:
    """An output root on a local folder or an object store. ``root`` is where the layout functions start: a ``Path``
    (local) or a ``PurePosixPath`` ``bucket/prefix`` (S3); every method takes such locations."""

    def __init__(self, uri: str | Path):
        self.scheme = uri_scheme(uri)
        if self.scheme is None:
            self.uri = str(uri)
            self.root: PurePath = Path(uri)
            self.fs = None
        elif self.scheme == "s3":
            self.uri = normalise_uri(uri)
            bucket_prefix = self.uri[len("s3://"):]
            if not bucket_prefix or bucket_prefix.startswith("/"):
                from pipeline.errors import OptionError

                raise OptionError("--root", [f"{uri}: expected s3://BUCKET[/PREFIX]"])
            self.root = PurePosixPath(bucket_prefix)
            self.fs = s3_filesystem()
        else:
            from pipeline.errors import OptionError

            raise OptionError("--root", [f"{uri}: unsupported scheme {self.scheme}://; supported: a local folder, "
                                         + ", ".join(f"{s}://" for s in SCHEMES)])

    @classmethod
    def open(cls, uri: "str | Path | Store") -> "Store":
        return uri if isinstance(uri, Store) else cls(uri)

    @property
    def local(self) -> bool:
        return self.fs is None

    def __repr__(self) -> str:
        return f"Store({self.uri!r})"

    def url(self, loc: PurePath) -> str:
        """A location as the user would write it (``s3://bucket/prefix/maps/city`` or a local path)."""
        return str(loc) if self.local else f"{self.scheme}://{loc.as_posix()}"

    # objects ------------------------------------------------------------------------------------------------------
    def read_bytes(self, loc: PurePath) -> bytes:
        """The bytes of one object; FileNotFoundError when absent."""
        if self.local:
            return Path(loc).read_bytes()
        return self.fs.cat_file(loc.as_posix())

    def exists(self, loc: PurePath) -> bool:
        if self.local:
            return Path(loc).exists()
        return self.fs.exists(loc.as_posix())

    def listdir(self, loc: PurePath) -> list[str]:
        """Names directly under ``loc`` (objects and "directories"), sorted; [] when there is none."""
        if self.local:
            try:
                return sorted(os.listdir(loc))
            except (FileNotFoundError, NotADirectoryError):
                return []
        try:
            entries = self.fs.ls(loc.as_posix(), detail=False, refresh=True)
        except FileNotFoundError:
            return []
        return sorted(PurePosixPath(e).name for e in entries if PurePosixPath(e) != loc)

    def walk_files(self, loc: PurePath) -> Iterator[tuple[str, int]]:
        """(path relative to ``loc``, bytes) of every object under ``loc``, sorted."""
        if self.local:
            base = Path(loc)
            for p in sorted(base.rglob("*")):
                if p.is_file():
                    yield p.relative_to(base).as_posix(), p.stat().st_size
            return
        prefix = loc.as_posix().rstrip("/") + "/"
        found = self.fs.find(loc.as_posix(), detail=True, withdirs=False)
        for key in sorted(found):
            if key.startswith(prefix):
                yield key[len(prefix):], int(found[key].get("size") or 0)

    def objects_under(self, loc: PurePath) -> dict[str, tuple[int, str, float]]:
        """{path relative to ``loc``: (bytes, version tag, modification time in unix s)} of the object ``loc`` itself
        (the key ``""``) or of every object under it; {} when there is none. The tag is the S3 ETag (local: size and
        mtime in ns)."""
        if self.local:
            base = Path(loc)
            paths = {"": base} if base.is_file() else {rel: base / rel for rel, _ in self.walk_files(base)}
            out = {}
            for rel, p in paths.items():
                st = p.stat()
                out[rel] = (st.st_size, f"{st.st_mtime_ns}-{st.st_size}", st.st_mtime)
            return out
        key = loc.as_posix().rstrip("/")
        try:
            found = self.fs.find(key, detail=True, withdirs=False)
        except FileNotFoundError:
            return {}
        out = {}
        for k, info in found.items():
            if k == key or k.startswith(key + "/"):
                stamp = info.get("LastModified")
                out[k[len(key) + 1:]] = (int(info.get("size") or 0), str(info.get("ETag") or stamp),
                                         stamp.timestamp() if stamp is not None else 0.0)
        return out

    def walk_objects(self, loc: PurePath) -> dict[str, tuple[int, float]]:
        """{path relative to ``loc``: (bytes, modification time in unix s)} of every object under ``loc``."""
        if self.local:
            out = {}
            for rel, _ in self.walk_files(loc):
                st = (Path(loc) / rel).lstat()
                out[rel] = (st.st_size, max(st.st_mtime, st.st_ctime))
            return out
        prefix = loc.as_posix().rstrip("/") + "/"
        found = self.fs.find(loc.as_posix(), detail=True, withdirs=False)
        out = {}
        for key, info in found.items():
            if key.startswith(prefix):
                stamp = info.get("LastModified")
                out[key[len(prefix):]] = (int(info.get("size") or 0), stamp.timestamp() if stamp is not None else 0.0)
        return out

    def put_bytes(self, loc: PurePath, data: bytes) -> None:
        """Write (or replace) one object atomically: a reader sees the old bytes or the new ones, never a part.
        Local: temporary file, fsync, ``os.replace``; S3: one PUT."""
        if self.local:
            atomic_write_bytes(Path(loc), data)
            return
        self.fs.pipe_file(loc.as_posix(), data)

    def create(self, loc: PurePath, data: bytes) -> bool:
        """Write ``loc`` only if no object is there (a commit marker, a lock object): True when this call created it,
        False when one existed (nothing is changed then). Local: a complete temporary file hard-linked into place
        (``link`` fails when the name exists); S3: a PUT with ``If-None-Match: *`` (a conditional put: of two
        writers, exactly one succeeds)."""
        if self.local:
            path = Path(loc)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            try:
                os.link(tmp, path)
            except FileExistsError:
                return False
            finally:
                tmp.unlink(missing_ok=True)
            return True
        try:
            self.fs.pipe_file(loc.as_posix(), data, mode="create")
        except FileExistsError:
            return False
        return True

    def etag(self, loc: PurePath) -> str | None:
        """The object's version tag (S3 ETag; local: mtime and size), None when absent."""
        if self.local:
            try:
                st = os.stat(loc)
            except FileNotFoundError:
                return None
            return f"{st.st_mtime_ns}-{st.st_size}"
        try:
            return self.fs.call_s3("head_object", **self._bk(loc))["ETag"]
        except FileNotFoundError:
            return None

    def replace_if(self, loc: PurePath, data: bytes, etag: str) -> bool:
        """Replace ``loc`` only while it still is the version ``etag`` (S3: ``If-Match``); False when it changed."""
        if self.local:
            raise NotImplementedError("replace_if is an object-store operation (local locks are flock)")
        try:
            self.fs.call_s3("put_object", **self._bk(loc), Body=data, IfMatch=etag)
        except (OSError, FileExistsError) as exc:
            if _precondition_failed(exc):
                return False
            raise
        return True

    def delete_if(self, loc: PurePath, etag: str) -> bool:
        """Delete ``loc`` only while it still is the version ``etag`` (S3: ``If-Match``); False when it changed."""
        if self.local:
            raise NotImplementedError("delete_if is an object-store operation (local locks are flock)")
        try:
            self.fs.call_s3("delete_object", **self._bk(loc), IfMatch=etag)
        except FileNotFoundError:
            return False
        except OSError as exc:
            if _precondition_failed(exc):
                return False
            raise
        return True

    def delete(self, loc: PurePath) -> None:
        """Remove one object (absent: nothing to do)."""
        if self.local:
            Path(loc).unlink(missing_ok=True)
            return
        try:
            self.fs.rm_file(loc.as_posix())
        except FileNotFoundError:
            pass

    def delete_tree(self, loc: PurePath) -> None:
        """Remove everything under ``loc``."""
        if self.local:
            import shutil

            shutil.rmtree(loc, ignore_errors=True)
            return
        keys = [k for k, _ in self.walk_files(loc)]
        if keys:
            self.fs.rm([f"{loc.as_posix()}/{k}" for k in keys])

    def upload_file(self, local: Path, loc: PurePath) -> None:
        if self.local:
            import shutil

            Path(loc).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(local, loc)
            return
        self.fs.put_file(str(local), loc.as_posix())

    def upload_files(self, pairs: list[tuple[Path, PurePath]]) -> None:
        """Upload local files to their locations (S3: ``TRANSFERS`` at a time: s3fs reads a file below its 50 MB
        chunk whole, so a batch of all of a drive's scans held them all in memory: 3.2 GB in a demo ingest task)."""
        if not pairs:
            return
        if self.local or len(pairs) == 1:
            for local, loc in pairs:
                self.upload_file(local, loc)
            return
        self.fs.put([str(a) for a, _ in pairs], [b.as_posix() for _, b in pairs], batch_size=TRANSFERS)

    def download_files(self, pairs: list[tuple[PurePath, Path]]) -> None:
        """Copy objects into local files, each written under a temporary name and renamed into place (a reader of
        the local file sees it whole or not at all). S3: one batched, concurrent call."""
        if not pairs:
            return
        tmps = [dest.with_name(f".{dest.name}.dl-{uuid.uuid4().hex[:8]}") for _, dest in pairs]
        for t in tmps:
            t.parent.mkdir(parents=True, exist_ok=True)
        try:
            if self.local:
                import shutil

                for (loc, _), t in zip(pairs, tmps):
                    shutil.copyfile(loc, t)
            else:
                self.fs.get([loc.as_posix() for loc, _ in pairs], [str(t) for t in tmps], batch_size=TRANSFERS)
            for (_, dest), t in zip(pairs, tmps):
                os.replace(t, dest)
        finally:
            for t in tmps:
                t.unlink(missing_ok=True)

    def copy(self, src: PurePath, dst: PurePath) -> None:
        """Copy one object within the store (S3: a server-side copy, no bytes through this process)."""
        if self.local:
            import shutil

            Path(dst).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            return
        self.fs.copy(src.as_posix(), dst.as_posix())

    def download_tree(self, loc: PurePath, dest: Path) -> list[str]:
        """Copy every object under ``loc`` into the local folder ``dest``; returns the relative paths."""
        rels = [rel for rel, _ in self.walk_files(loc)]
        if not rels:
            return []
        if self.local:
            import shutil

            for rel in rels:
                target = inside(dest, rel)
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(Path(loc) / rel, target)
            return rels
        targets = [str(inside(dest, rel)) for rel in rels]
        for t in targets:
            Path(t).parent.mkdir(parents=True, exist_ok=True)
        self.fs.get([f"{loc.as_posix()}/{rel}" for rel in rels], targets)
        return rels

    def _bk(self, loc: PurePath) -> dict[str, str]:
        bucket, _, key = loc.as_posix().partition("/")
        return {"Bucket": bucket, "Key": key}


def _named_errors(method):
    """``method`` of ``Store`` with the object-store client's own errors (botocore, aiobotocore, aiohttp: an endpoint
    down, credentials missing or refused, a bucket absent) raised as one ``ObjectStoreError`` naming the location's
    URI and the endpoint (``object_store_error_line``). A local root calls the method as it is."""
    import functools
    import inspect

    def named(self: "Store", args: tuple, exc: Exception) -> Exception | None:
        line = object_store_error_line(exc)
        if line is None:
            return None
        from pipeline.errors import ObjectStoreError

        return ObjectStoreError.at(self.url(_asked_for(self, args)), line)

    if inspect.isgeneratorfunction(method):
        @functools.wraps(method)
        def walker(self: "Store", *args, **kwargs):
            try:
                yield from method(self, *args, **kwargs)
            except Exception as exc:
                err = named(self, args, exc) if self.fs is not None else None
                if err is None:
                    raise
                raise err from exc

        return walker

    @functools.wraps(method)
    def wrapper(self: "Store", *args, **kwargs):
        if self.fs is None:
            return method(self, *args, **kwargs)
        try:
            return method(self, *args, **kwargs)
        except Exception as exc:
            err = named(self, args, exc)
            if err is None:
                raise
            raise err from exc

    return wrapper


def _asked_for(store: "Store", args: tuple) -> PurePath:
    """The store location a call of a ``Store`` method names: its first argument, or the first store location of a
    list of (local, store) / (store, local) pairs; the root when none."""
    first = args[0] if args else None
    if isinstance(first, list) and first and isinstance(first[0], tuple):
        first = next((p for p in first[0] if not isinstance(p, Path)), first[0][0])
    return first if isinstance(first, PurePath) else store.root


for _name in ("read_bytes", "exists", "listdir", "walk_files", "objects_under", "walk_objects", "put_bytes", "create",
              "etag", "replace_if", "delete_if", "delete", "delete_tree", "upload_file", "upload_files",
              "download_files", "copy", "download_tree"):
    setattr(Store, _name, _named_errors(getattr(Store, _name)))


def _precondition_failed(exc: BaseException) -> bool:
    text = f"{exc} {getattr(exc, '__cause__', '')}"
    return "PreconditionFailed" in text or "pre-condition" in text.lower() or "412" in text \
        or isinstance(exc, FileExistsError)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """A local file replaced atomically: a temporary file beside it, fsynced, then ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def object_store_error_line(exc: BaseException) -> str | None:
    """One line for a failure of the object store's client (endpoint unreachable, credentials missing or refused,
    bucket absent), or None when ``exc`` is not one: botocore, aiobotocore and aiohttp errors are not OSErrors."""
    clients = ("botocore", "aiobotocore", "aiohttp", "s3fs")
    if not any(t.__module__.split(".")[0] in clients for t in type(exc).__mro__):
        return None
    endpoint = os.environ.get("AWS_ENDPOINT_URL") or "the AWS default endpoint"
    return (f"the object store ({endpoint}) failed: {type(exc).__name__}: {exc}; hint: check AWS_ENDPOINT_URL, the "
            "credentials (AWS_ACCESS_KEY_ID / AWS_PROFILE) and that the bucket exists")


def s3_filesystem():
    """An ``s3fs`` file system configured from the standard AWS environment (``AWS_ENDPOINT_URL`` for MinIO, Ceph or
    a local server; credentials from the environment or ``AWS_PROFILE``). Cached per process by fsspec."""
    try:
        import s3fs
    except ImportError as exc:  # a core dependency; only a broken install lacks it
        from pipeline.errors import ConfigError

        raise ConfigError("s3://", [f"the s3fs package is missing ({exc}); reinstall cornermap"]) from exc
    return s3fs.S3FileSystem(use_listings_cache=False,
                             config_kwargs={"retries": {"max_attempts": 3, "mode": "standard"}})
