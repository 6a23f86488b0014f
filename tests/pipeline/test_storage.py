"""The store's contract, the same tests on both backends: a local folder and S3 (a real S3 API server, moto's server
mode on 127.0.0.1, started by the session: ``tests/conftest.py`` ``s3_env``)."""
from __future__ import annotations

import threading
import time
from pathlib import Path, PurePosixPath

import pytest

from pipeline import storage
from pipeline.errors import OptionError, RunLockedError
from pipeline.leases import LeaseLocks
from pipeline.storage import Store


@pytest.fixture(params=["local", "s3"])
def store(request, tmp_path) -> Store:
    if request.param == "local":
        return Store.open(tmp_path / "root")
    return Store.open(request.getfixturevalue("s3_root"))


def test_the_layout_is_the_same_on_both_backends(tmp_path):
    local, remote = Path(tmp_path), PurePosixPath("bucket/prefix")
    for root in (local, remote):
        d = storage.dataset_dir(root, "scans_raw", "0123456789abcdef0123")
        rel = lambda p: p.relative_to(root).as_posix()  # noqa: E731
        assert rel(d) == "datasets/scans_raw/0123456789abcdef"
        assert rel(storage.dataset_manifest(d)) == "datasets/scans_raw/0123456789abcdef/_manifest.json"
        assert rel(storage.part_marker(d, "drive_0")) == "datasets/scans_raw/0123456789abcdef/_parts/drive_0.json"
        assert rel(storage.artifacts_dir(d, "all")) == "datasets/scans_raw/0123456789abcdef/artifacts/all"
        m = storage.map_dir(root, "city")
        assert rel(storage.latest_file(m)) == "maps/city/LATEST"
        assert rel(storage.version_manifest(storage.version_dir(m, 3))) == "maps/city/v0003/manifest.json"
        assert rel(storage.identity_file(m)) == "maps/city/map.json"
        assert rel(storage.gate_file(m, 12)) == "maps/city/gate/v0012.json"
        assert storage.root_of_map(m) == root
        assert rel(storage.tmp_dir(root, "x")) == "tmp/x" and rel(storage.locks_dir(root)) == "locks"


@pytest.mark.parametrize("value,scheme", [("s3://b/p", "s3"), (Path("s3://b/p"), "s3"), ("S3://b", "s3"),
                                          ("gs://b/p", "gs"), ("runs/city", None), ("/abs/s3:x", None),
                                          ("./s3:/b", None), ("s3", None)])
def test_uris_are_told_from_folders(value, scheme):
    assert storage.uri_scheme(value) == scheme
    if scheme is not None:
        with pytest.raises(OptionError, match="--root"):
            storage.refuse_uri(value, "--root")
    assert storage.normalise_uri(Path("s3://b/p/")) == "s3://b/p"


def test_an_unsupported_scheme_or_a_bucketless_uri_is_a_usage_error():
    for bad in ("gs://b/p", "s3://"):
        with pytest.raises(OptionError):
            Store.open(bad)


def test_objects_round_trip_and_replace_whole(store):
    loc = storage.latest_file(storage.map_dir(store.root, "city"))
    assert not store.exists(loc) and store.etag(loc) is None
    with pytest.raises(FileNotFoundError):
        store.read_bytes(loc)
    store.put_bytes(loc, b"v0001 " + b"a" * 64 + b"\n")
    store.put_bytes(loc, b"v0002 " + b"b" * 64 + b"\n")
    assert store.read_bytes(loc) == b"v0002 " + b"b" * 64 + b"\n" and store.exists(loc)
    assert store.listdir(storage.map_dir(store.root, "city")) == ["LATEST"]
    assert store.listdir(storage.map_dir(store.root, "nowhere")) == []


def test_readers_never_see_a_part_of_a_replaced_object(store):
    loc = storage.identity_file(storage.map_dir(store.root, "city"))
    a, b = b"A" * 200_000, b"B" * 300_000
    store.put_bytes(loc, a)
    seen, stop = set(), threading.Event()

    def read():
        while not stop.is_set():
            got = store.read_bytes(loc)
            seen.add((got[:1], len(got)))

    t = threading.Thread(target=read)
    t.start()
    for _ in range(10):
        store.put_bytes(loc, b)
        store.put_bytes(loc, a)
    stop.set()
    t.join()
    assert seen <= {(b"A", len(a)), (b"B", len(b))}, seen


def test_create_is_won_by_exactly_one_of_many_writers(store):
    loc = storage.version_manifest(storage.version_dir(storage.map_dir(store.root, "city"), 1))
    results: list[tuple[int, bool]] = []
    barrier = threading.Barrier(6)

    def writer(i):
        barrier.wait()
        results.append((i, store.create(loc, f"writer {i}".encode())))

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    winners = [i for i, ok in results if ok]
    assert len(winners) == 1 and store.read_bytes(loc) == f"writer {winners[0]}".encode()
    assert not store.create(loc, b"late") and store.read_bytes(loc) == f"writer {winners[0]}".encode()


def test_trees_walk_download_and_delete(store, tmp_path):
    vdir = storage.version_dir(storage.map_dir(store.root, "city"), 1)
    src = tmp_path / "src"
    (src / "tiles" / "0_0").mkdir(parents=True)
    (src / "tiles" / "0_0" / "corners.parquet").write_bytes(b"p" * 1000)
    (src / "a.json").write_text("{}")
    for rel in ("a.json", "tiles/0_0/corners.parquet"):
        store.upload_file(src / rel, vdir / rel)
    assert list(store.walk_files(vdir)) == [("a.json", 2), ("tiles/0_0/corners.parquet", 1000)]
    got = store.download_tree(vdir, tmp_path / "copy")
    assert got == ["a.json", "tiles/0_0/corners.parquet"]
    assert (tmp_path / "copy" / "tiles" / "0_0" / "corners.parquet").read_bytes() == b"p" * 1000
    store.delete_tree(vdir)
    assert list(store.walk_files(vdir)) == [] and store.listdir(vdir) == []


def test_conditional_replace_and_delete_follow_the_etag(s3_root):
    store = Store.open(s3_root)
    loc = storage.locks_dir(store.root) / "k.lock" / "x"
    assert store.create(loc, b"one")
    tag = store.etag(loc)
    assert not store.replace_if(loc, b"two", '"0000"') and store.read_bytes(loc) == b"one"
    assert store.replace_if(loc, b"two", tag) and store.read_bytes(loc) == b"two"
    assert not store.delete_if(loc, tag) and store.exists(loc)  # tag is the old version's
    assert store.delete_if(loc, store.etag(loc)) and not store.exists(loc)


def test_lease_locks_exclude_like_file_locks(s3_root):
    a, b = LeaseLocks(Store.open(s3_root), ttl_s=30, holder="A"), LeaseLocks(Store.open(s3_root), ttl_s=30, holder="B")
    with a.hold("root", exclusive=False, what="run A"):
        with b.hold("root", exclusive=False, what="run B"):  # shared with shared: both
            pass
        with pytest.raises(RunLockedError, match="run A"):
            b.hold("root", exclusive=True, what="gc").__enter__()
        with a.hold("root", exclusive=False):  # nested in the same process
            pass
    with b.hold("root", exclusive=True, what="gc"):
        with pytest.raises(RunLockedError, match="exit 75"):
            a.hold("root", exclusive=False, what="run A").__enter__()
    with a.hold("root", exclusive=True):  # released: free again, and nothing left behind
        pass
    assert list(Store.open(s3_root).walk_files(storage.locks_dir(Store.open(s3_root).root))) == []


def test_a_dead_holders_lease_expires_and_is_taken_over_once(s3_root):
    store = Store.open(s3_root)
    dead = LeaseLocks(store, ttl_s=1.0, holder="dead")
    dead._acquire_exclusive("map-city", "a killed publisher")  # taken, never renewed nor released: a dead holder
    live = LeaseLocks(store, ttl_s=30, holder="live")
    with pytest.raises(RunLockedError, match="a killed publisher"):
        live.hold("map-city", exclusive=True).__enter__()
    time.sleep(1.2)
    takers = [LeaseLocks(store, ttl_s=30, holder=f"taker{i}") for i in range(4)]
    won, barrier = [], threading.Barrier(4)

    def take(locks):
        barrier.wait()
        try:
            locks._acquire_exclusive("map-city", "taker")
            won.append(locks)
        except RunLockedError:
            pass

    threads = [threading.Thread(target=take, args=(t,)) for t in takers]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(won) == 1  # of several takers of an expired lease exactly one wins


def test_a_lease_is_renewed_while_held(s3_root):
    store = Store.open(s3_root)
    holder = LeaseLocks(store, ttl_s=0.9, holder="long")
    other = LeaseLocks(store, ttl_s=30, holder="other")
    with holder.hold("map-city", exclusive=True, what="long publish"):
        time.sleep(2.0)  # > 2 TTLs: alive only because the holder renews it
        with pytest.raises(RunLockedError, match="long publish"):
            other.hold("map-city", exclusive=True).__enter__()
    with other.hold("map-city", exclusive=True):
        pass


def test_gc_removes_a_dead_holders_lease_and_keeps_a_live_one(s3_root):
    from pipeline.store_maps import gc_uncommitted

    store = Store.open(s3_root)
    LeaseLocks(store, ttl_s=0.5, holder="dead")._acquire_exclusive("map-a", "killed")
    with LeaseLocks(store, ttl_s=30, holder="live").hold("map-b", exclusive=True, what="alive"):
        time.sleep(0.6)
        found = gc_uncommitted(store, min_age_h=0, apply=True)
        assert [why for _, why in found] == ["lease expired: its holder is gone"]
        assert found[0][0].endswith("/locks/map-a.lock/x")
        assert [k for k, _ in store.walk_files(storage.locks_dir(store.root))] == ["map-b.lock/x"]


def test_nested_holds_of_one_process_share_the_lock_on_both_backends(tmp_path, s3_root):
    """Within one process a hold nests in a hold of the same lock (shared in exclusive too) and releases with the
    outer one; an exclusive hold inside a shared one is refused (it would deadlock against itself)."""
    import pipeline.leases
    import pipeline.locks
    from pipeline.locks import FileLocks

    for locks in (FileLocks(tmp_path / "root"), LeaseLocks(Store.open(s3_root), ttl_s=30, holder="A")):
        with locks.hold("map-city", exclusive=True):
            with locks.hold("map-city", exclusive=False):
                pass
        with locks.hold("map-city", exclusive=False):
            with pytest.raises(RuntimeError, match="cannot be made exclusive"):
                locks.hold("map-city", exclusive=True).__enter__()
        assert not pipeline.locks._HELD and not pipeline.leases._HELD  # the outer holds released them
    with LeaseLocks(Store.open(s3_root), ttl_s=30, holder="B").hold("map-city", exclusive=True):  # free for another
        pass


def test_every_store_operation_on_an_unreachable_store_raises_one_named_error(monkeypatch, tmp_path):
    """An endpoint nobody listens on: each operation of an S3 ``Store`` (reads, listings, a walk, writes, a
    conditional put, transfers) raises ``ObjectStoreError`` (a ``DatasetIOError``, an ``OSError``), one line that
    starts with the URI of the location asked for and names the endpoint, never the client's own exception."""
    import socket

    import s3fs

    from pipeline.errors import DatasetIOError, ObjectStoreError

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{port}")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    local = tmp_path / "f.bin"
    local.write_bytes(b"x")
    s3fs.S3FileSystem.clear_instance_cache()  # fsspec caches a file system per process: one of this test's env
    try:
        store = Store.open("s3://hcmaps/root")
        loc = store.root / "maps" / "city" / "LATEST"
        calls = {
            "read_bytes": lambda: store.read_bytes(loc),
            "exists": lambda: store.exists(loc),
            "listdir": lambda: store.listdir(loc),
            "walk_files": lambda: list(store.walk_files(loc)),
            "objects_under": lambda: store.objects_under(loc),
            "put_bytes": lambda: store.put_bytes(loc, b"v0001"),
            "create": lambda: store.create(loc, b"v0001"),
            "upload_files": lambda: store.upload_files([(local, loc), (local, loc.with_name("B"))]),
            "download_files": lambda: store.download_files([(loc, tmp_path / "got")]),
        }
        for name, call in calls.items():
            with pytest.raises(ObjectStoreError) as err:
                call()
            text = str(err.value)
            assert isinstance(err.value, (DatasetIOError, OSError)), name
            assert text.startswith("s3://hcmaps/root/maps/city/LATEST: the object store"), (name, text)
            assert f"127.0.0.1:{port}" in text and "\n" not in text, (name, text)
            assert err.value.uri == "s3://hcmaps/root/maps/city/LATEST" and err.value.line in text, name
    finally:
        s3fs.S3FileSystem.clear_instance_cache()  # the next test's env gets its own


def test_a_local_store_raises_the_file_systems_own_errors(tmp_path):
    """A local root is the file system: an absent file is FileNotFoundError, as before (no wrapping)."""
    store = Store.open(tmp_path / "root")
    with pytest.raises(FileNotFoundError):
        store.read_bytes(store.root / "maps" / "city" / "LATEST")
