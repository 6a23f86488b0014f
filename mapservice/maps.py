"""A map as a maintained thing: its identity (pinned frame, tile size, area, drive set), its locks, rollback.

Files under ``ROOT/maps/NAME/`` besides the versions (``pipeline/versioned.py``)::

    map.json        the identity: schema, name, enu_origin (lat_deg, lon_deg, h_m WGS84), tile_size_m,
                    max_radius_km, created_utc, check_drive (optional) and the drive set (name, drive.yaml path,
                    fingerprints, added_utc, the version that added it); replaced atomically
    gate/vNNNN.json the regression gate's comparison for candidate vNNNN

A writer of the map holds ``pipeline.locks.writer_locks`` (the root shared, the map exclusive; ``run_lock``).
``MapHome`` is the map as a writer sees it on a local root or an ``s3://`` one alike (identity, LATEST, versions,
gate records, locks).

Knows nothing about LiDAR: a drive is a ``drive.yaml`` path and its ``pipeline.fingerprint.drive_fingerprint``.
"""
from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any, ContextManager, Iterable, Iterator

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from pipeline import storage
from pipeline.errors import ConfigError, DatasetIOError, UnknownNameError
from pipeline.names import check_name
from stages.common.geodesy import EnuOrigin
from stages.common.tiling import DEFAULT_TILE_SIZE_M

IDENTITY_NAME = storage.IDENTITY
IDENTITY_SCHEMA = "cornermap.map-identity/1"
GATE_DIR = storage.GATE
# A map's area: drives whose GNSS fixes lie farther from the origin are refused (exit 3). A local ENU frame is a
# tangent plane: at distance d its up axis leans d / R from the local vertical and the ground falls d^2 / (2 R) below
# its horizontal plane (R = 6371 km): 10 km -> 0.09 deg and 7.8 m; 70 km -> 0.63 deg and 385 m (docs/maintenance.md).
DEFAULT_MAX_RADIUS_KM = 10.0
MAX_RADIUS_LIMIT_KM = 100.0
# The pinned frame: parsed, validated and compared by the one origin type (its ranges, its same-frame tolerance).
Origin = Annotated[EnuOrigin, BeforeValidator(EnuOrigin.validate)]


class MapDrive(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    path: str  # absolute drive.yaml
    fingerprint: str  # pipeline.fingerprint.drive_fingerprint: the files' names, sizes (and mtimes of large ones)
    content: str | None = None  # sha256 of what the drive file references (`cornermap drive check --content`)
    added_utc: str
    added_in: int | None = None  # the version that first held it


class CheckDrive(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    path: str  # absolute drive.yaml localized by the regression gate
    reference: str | None = None  # truth TUM; None: the drive's own pose graph ("map")


class MapIdentity(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_: str = Field(IDENTITY_SCHEMA, alias="schema")
    name: str
    enu_origin: Origin
    tile_size_m: float = Field(DEFAULT_TILE_SIZE_M, gt=0, le=10000)
    max_radius_km: float = Field(DEFAULT_MAX_RADIUS_KM, gt=0, le=MAX_RADIUS_LIMIT_KM)
    created_utc: str
    check_drive: CheckDrive | None = None
    drives: list[MapDrive] = []

    def dump(self) -> dict[str, Any]:
        return self.model_dump(mode="json", by_alias=True)


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def map_dir(root: Path, name: str) -> Path:
    return storage.map_dir(Path(root), check_name(name, "map", "--map"))


def read_identity(mdir: Path) -> MapIdentity | None:
    """The map's identity, None when the map has none (an unpinned map); ConfigError when it is malformed."""
    path = storage.identity_file(Path(mdir))
    if not path.is_file():
        return None
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(str(path), [f"not readable JSON: {exc}"]) from exc
    return parse_identity(raw, str(path))


def parse_identity(raw: bytes, where: str) -> MapIdentity:
    """An identity document's bytes -> MapIdentity; ConfigError naming ``where`` when malformed."""
    try:
        doc = json.loads(raw.decode("utf-8"))
    except ValueError as exc:
        raise ConfigError(where, [f"not readable JSON: {exc}"]) from exc
    if isinstance(doc, dict) and doc.get("schema") != IDENTITY_SCHEMA:
        raise ConfigError(where, [f"schema {doc.get('schema')!r}; expected {IDENTITY_SCHEMA!r}"])
    try:
        return MapIdentity.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(where, [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()]) from None


def require_identity(mdir: Path) -> MapIdentity:
    ident = read_identity(mdir)
    if ident is None:
        raise UnknownNameError(f"{mdir}: no {IDENTITY_NAME}; hint: cornermap maps create --root ROOT --map "
                               f"{mdir.name} --origin LAT,LON,H")
    return ident


def write_identity(mdir: Path, ident: MapIdentity) -> None:
    """Atomic replace (temp file + fsync + rename): a reader sees the old identity or the new one."""
    mdir.mkdir(parents=True, exist_ok=True)
    tmp = mdir / f".{IDENTITY_NAME}.tmp-{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(json.dumps(ident.dump(), indent=1) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, mdir / IDENTITY_NAME)


def create_map(root: "Path | str", name: str, origin: dict[str, float], tile_size_m: float = DEFAULT_TILE_SIZE_M,
               check_drive: CheckDrive | None = None, max_radius_km: float = DEFAULT_MAX_RADIUS_KM) -> MapIdentity:
    """Write a new map's identity (a local root or an ``s3://`` one: ``MapHome``); refuses a map that already has
    one, or versions in another frame."""
    home = MapHome(root, name)
    where = home.store.url(storage.identity_file(home.mdir))
    if home.identity() is not None:
        raise ConfigError(f"cornermap maps create --map {name}", [f"{where} exists; a map's frame is never changed "
                                                                  "(make a new map)"])
    ident = MapIdentity(name=name, enu_origin=origin, tile_size_m=tile_size_m, created_utc=utc_now(),
                        check_drive=check_drive, max_radius_km=max_radius_km)
    with home.view(whole=()) as view:
        published = latest_origin(view)
    if published is not None and not EnuOrigin.validate(published).same_frame(ident.enu_origin):
        raise ConfigError(f"cornermap maps create --map {name}",
                          [f"its published versions are in the frame {EnuOrigin.validate(published).text()}, not "
                           f"{ident.enu_origin.text()}; pass that origin or make a new map"])
    if home.local:
        write_identity(Path(home.mdir), ident)
    elif not home.store.create(storage.identity_file(home.mdir), (json.dumps(ident.dump(), indent=1) + "\n").encode()):
        raise ConfigError(f"cornermap maps create --map {name}", [f"{where} exists; a map's frame is never changed"])
    return ident


def latest_origin(mdir: Path) -> dict[str, float] | None:
    """The ENU origin of the version LATEST names (None without one)."""
    from pipeline.version_read import read_latest, read_manifest, version_name

    if not storage.latest_file(Path(mdir)).is_file():
        return None
    latest = read_latest(mdir)
    if latest is None:
        return None
    origin = read_manifest(Path(mdir) / version_name(latest))[0].get("enu_origin")
    if not isinstance(origin, dict):
        return None
    return {"lat_deg": float(origin["lat_deg"]), "lon_deg": float(origin["lon_deg"]),
            "h_m": float(origin.get("h_m", 0.0))}  # the manifest also names the ellipsoid (always WGS84)


def pinned_frame(root: Path, name: str, origin: dict[str, float] | None) -> tuple[dict[str, float] | None,
                                                                                  float | None]:
    """The (origin, tile size) a build of map NAME must use: the identity's, else LATEST's origin; ``origin``
    (from --origin) must agree with it. ConfigError (exit 1) when it does not."""
    mdir = map_dir(root, name)
    ident = read_identity(mdir)
    pinned, source, tile = None, "", None
    if ident is not None:
        pinned, source, tile = ident.enu_origin.plain(), f"its identity {mdir / IDENTITY_NAME}", ident.tile_size_m
    else:
        pinned, source = latest_origin(mdir), f"its LATEST version in {mdir}"
    if pinned is None:
        return origin, None
    if origin is not None and not EnuOrigin.validate(origin).same_frame(EnuOrigin.validate(pinned)):
        raise ConfigError("--origin", [f"map {name!r} is pinned to {EnuOrigin.validate(pinned).text()} by {source}; "
                                       f"--origin {EnuOrigin.validate(origin).text()} would move its frame (refused)"])
    return pinned, tile


@contextmanager
def run_lock(mdir: Path) -> Iterator[None]:
    """A whole run that writes map ``ROOT/maps/NAME``: its root shared and the map exclusive
    (``pipeline.locks.writer_locks``), non-waiting, released by the kernel when the holder dies. RunLockedError
    (exit 75) naming the holder when another writer has either; nothing is written then."""
    from pipeline.locks import writer_locks

    mdir = Path(mdir)
    with writer_locks(storage.root_of_map(mdir), mdir.name):
        yield


def check_free_disk(root: Path, min_free_gib: float) -> None:
    """DatasetIOError (exit 1) with the numbers when the file system of ``root`` has less free space."""
    probe = Path(root)
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free / 2**30
    if free < min_free_gib:
        raise DatasetIOError(f"{probe}: {free:.2f} GiB free, {min_free_gib:.2f} GiB required to start a rebuild; "
                             "hint: cornermap gc --root ROOT --apply, or free space, or lower --min-free-gib")


def published_version(plan: Any) -> int | None:
    """The map version the plan's tiles stage published (its committed ``map_tiles`` dataset), None without one."""
    import pyarrow.parquet as pq

    from pipeline.names import inside
    from pipeline.store import data_root

    sp = next((sp for sp in plan.stages.values() if "map_tiles" in sp.outputs.values()), None)
    if sp is None:
        return None
    droot = data_root(plan.uri)
    m = droot.manifest("map_tiles", sp.fingerprint)
    if not m:
        return None
    droot.fetch("map_tiles", sp.fingerprint, [(f["path"], f.get("bytes")) for f in m["files"]])
    d = droot.dir("map_tiles", sp.fingerprint)
    for f in m["files"]:
        rows = pq.read_table(inside(d, f["path"]), columns=["version"]).to_pylist()
        if rows:
            return int(rows[0]["version"])
    return None


def stale_latest_note(plan: Any, name: str) -> str | None:
    """When the version this run's drive set published is not LATEST (an earlier run published it, and another
    drive set's version has been published since), the line that says so; None when it is LATEST."""
    import pyarrow.parquet as pq

    from pipeline.names import inside
    from pipeline.store import data_root
    from pipeline.versioned import read_latest, version_name

    for sp in plan.stages.values():
        for ds in sp.outputs.values():
            if ds != "map_tiles":
                continue
            droot = data_root(getattr(plan, "uri", None) or plan.root)  # a Plan, or what names its root
            m = droot.manifest(ds, sp.fingerprint)
            if not m or not m["files"]:
                return None
            first = m["files"][0]
            droot.fetch(ds, sp.fingerprint, [(first["path"], first.get("bytes"))])
            table = pq.read_table(inside(droot.dir(ds, sp.fingerprint), first["path"]),
                                  columns=["map_name", "version"]).to_pylist()
            mine = next((int(r["version"]) for r in table if r["map_name"] == name), None)
            if droot.remote:
                from pipeline.store_maps import read_latest_number

                latest = read_latest_number(droot.store, name)
            else:
                latest = read_latest(map_dir(plan.root, name))
            if mine is None or latest is None or latest == mine:
                return None
            return (f"note: map {name!r}: this drive set is version {version_name(mine)} (published by an earlier "
                    f"run), but LATEST is {version_name(latest)}; `cornermap tiles rollback --to "
                    f"{version_name(mine)}` serves it, `cornermap rebuild` adds drives to the map")
    return None


class MapHome:
    """Map NAME of an output root as a writer (``cornermap rebuild``, ``maps create``) sees it, on a local folder or
    an object store alike: its identity, LATEST, committed versions, gate records and writer locks. A local root is
    read and written in place (``ROOT/maps/NAME``); an ``s3://`` root through its ``Store`` (the identity and LATEST
    one PUT each, versions read from a local snapshot, ``pipeline.store_maps``)."""

    def __init__(self, root: "str | Path", name: str):
        from pipeline.storage import Store, uri_scheme

        check_name(name, "map", "--map")
        self.store = Store.open(root if uri_scheme(root) is not None else Path(root).resolve())
        self.name = name
        self.mdir = storage.map_dir(self.store.root, name)  # a Path (local) or bucket/prefix location

    @property
    def local(self) -> bool:
        return self.store.local

    @property
    def root(self) -> "str | Path":
        """The root as the engine takes it: a local ``Path`` or the ``s3://`` URI."""
        return Path(self.store.root) if self.local else self.store.uri

    def where(self) -> str:
        return self.store.url(self.mdir)

    def identity(self) -> MapIdentity | None:
        if self.local:
            return read_identity(Path(self.mdir))
        loc = storage.identity_file(self.mdir)
        try:
            raw = self.store.read_bytes(loc)
        except FileNotFoundError:
            return None
        return parse_identity(raw, self.store.url(loc))

    def require_identity(self) -> MapIdentity:
        ident = self.identity()
        if ident is None:
            raise UnknownNameError(f"{self.where()}: no {IDENTITY_NAME}; hint: cornermap maps create --root ROOT "
                                   f"--map {self.name} --origin LAT,LON,H")
        return ident

    def write_identity(self, ident: MapIdentity) -> None:
        """Replace the identity atomically (a reader sees the old one or the new one)."""
        if self.local:
            write_identity(Path(self.mdir), ident)
        else:
            self.store.put_bytes(storage.identity_file(self.mdir), (json.dumps(ident.dump(), indent=1) + "\n").encode())

    def latest(self) -> int | None:
        from pipeline.version_read import read_latest

        if self.local:
            return read_latest(Path(self.mdir)) if storage.latest_file(Path(self.mdir)).exists() else None
        from pipeline.store_maps import read_latest_number

        return read_latest_number(self.store, self.name)

    def run_lock(self) -> "ContextManager[None]":
        """``run_lock``: the root shared, the map exclusive (flock locally, leases on a store); exit 75 when held."""
        from pipeline.locks import writer_locks

        return writer_locks(self.store.root if self.local else self.store.uri, self.name)

    @contextmanager
    def view(self, whole: "Iterable[int] | str" = ()) -> Iterator[Path]:
        """A local map folder to read from: ``ROOT/maps/NAME`` itself, or on a store a snapshot (LATEST, identity,
        gate records, every committed manifest, the versions ``whole`` names in full) in a temporary folder of this
        process's scratch, removed after."""
        if self.local:
            yield Path(self.mdir)
            return
        import tempfile

        from pipeline.store_maps import snapshot_map

        with tempfile.TemporaryDirectory(prefix="cornermap-view-", dir=_scratch()) as tmp:
            yield snapshot_map(self.store, self.name, Path(tmp), whole=whole)

    def put_gate(self, local_mdir: Path, version: int) -> None:
        """Upload the gate record of ``version`` written in the local view ``local_mdir`` (on a store)."""
        if not self.local:
            self.store.put_bytes(storage.gate_file(self.mdir, version),
                                 storage.gate_file(Path(local_mdir), version).read_bytes())

    def move_latest(self, version: int) -> None:
        """Verify ``version``'s bytes (files against its manifest) and point LATEST at it; DataQualityError (LATEST
        unchanged) when it is not intact. The caller holds the map's lock."""
        from pipeline.errors import DataQualityError
        from pipeline.version_read import read_manifest, verify_version, version_name

        if self.local:
            from pipeline.versioned import publish_lock, write_latest

            mdir = Path(self.mdir)
            with publish_lock(mdir):
                problems = verify_version(storage.version_dir(mdir, version))
                if problems:
                    raise DataQualityError(f"{storage.version_dir(mdir, version)}: {problems[0]}; LATEST unchanged")
                write_latest(mdir, version)
            return
        with self.view(whole=[version]) as local:
            vdir = storage.version_dir(local, version)
            problems = verify_version(vdir)
            if problems:
                where = self.store.url(storage.version_dir(self.mdir, version))
                raise DataQualityError(f"{where}: {problems[0].replace(str(local), self.where())}; LATEST unchanged")
            sha = read_manifest(vdir)[1]
        self.store.put_bytes(storage.latest_file(self.mdir), f"{version_name(version)} {sha}\n".encode())


def _scratch() -> Path:
    base = storage.scratch_base()
    base.mkdir(parents=True, exist_ok=True)
    return base
