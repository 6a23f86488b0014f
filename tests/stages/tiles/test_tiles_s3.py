"""Published maps on S3 (a real S3 API server on 127.0.0.1: moto's server mode, ``tests/conftest.py`` ``s3_env``):
``cornermap tiles push`` commits versions to a bucket, ``tiles ls|verify|export`` and ``mapformat.loader.open_map``
read and check them from it, run as processes from a folder outside the checkout with the standard AWS environment.
A writer killed mid-commit leaves nothing visible; a version is committed once."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from pipeline import storage
from pipeline.errors import PublishConflictError
from pipeline.storage import Store
from pipeline.store_maps import list_versions, publish_version_to, push_map, push_version
from tests.stages.tiles.tiles_synth import publish_two_versions
from tests.test_cli_process import cornermap


@pytest.fixture(scope="module")
def local_root(tmp_path_factory) -> Path:
    return publish_two_versions(tmp_path_factory.mktemp("s3src"))


def _cm(*args, cwd, env) -> subprocess.CompletedProcess:
    return cornermap(*args, cwd=cwd, **env)


def test_push_ls_verify_export_and_load_from_a_bucket(local_root, s3_root, s3_env, tmp_path):
    work = tmp_path / "elsewhere"
    work.mkdir()
    res = _cm("tiles", "push", "--root", str(local_root), "--map", "city", "--to", s3_root, cwd=work, env=s3_env)
    assert res.returncode == 0 and "2 version(s) committed (v0001, v0002)" in res.stdout, res.stderr
    res = _cm("tiles", "push", "--root", str(local_root), "--map", "city", "--to", s3_root, cwd=work, env=s3_env)
    assert res.returncode == 0 and "already up to date" in res.stdout  # idempotent
    store = Store.open(s3_root)
    mdir = storage.map_dir(store.root, "city")
    assert store.read_bytes(storage.latest_file(mdir)) == (local_root / "maps/city/LATEST").read_bytes()

    res = _cm("tiles", "ls", "--root", s3_root, "--json", cwd=work, env=s3_env)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    local = json.loads(_cm("tiles", "ls", "--root", str(local_root), "--json", cwd=work, env=s3_env).stdout)
    assert doc["latest"] == "v0002" and doc["path"] == f"{s3_root}/maps/city"
    assert [(v["version"], v["manifest_sha256"], v["n_corners"]) for v in doc["versions"]] == \
        [(v["version"], v["manifest_sha256"], v["n_corners"]) for v in local["versions"]]

    for cmd in (("tiles", "log", "--json"), ("maps", "show", "--map", "city", "--json")):
        remote = _cm(*cmd, "--root", s3_root, cwd=work, env=s3_env)
        here = _cm(*cmd, "--root", str(local_root), cwd=work, env=s3_env)
        assert remote.returncode == 0 and here.returncode == 0, remote.stderr + here.stderr
        a, b = json.loads(remote.stdout), json.loads(here.stdout)
        if isinstance(a, dict):
            assert a.pop("path") == f"{s3_root}/maps/city" and b.pop("path") == str(local_root / "maps/city")
        assert a == b and a, cmd
    for cmd in (("tiles", "diff", "v1", "LATEST", "--json"),
                ("tiles", "query", "--at", "37.4979,127.0276", "--radius", "300", "--json")):
        remote = _cm(*cmd, "--root", s3_root, cwd=work, env=s3_env)
        here = _cm(*cmd, "--root", str(local_root), cwd=work, env=s3_env)
        assert remote.returncode == 0 and here.returncode == 0, remote.stderr + here.stderr
        a, b = json.loads(remote.stdout), json.loads(here.stdout)
        a.pop("path", None), b.pop("path", None)
        assert a == b and a, cmd
    res = _cm("tiles", "verify", "--all", "--root", s3_root, "--map", "city", cwd=work, env=s3_env)
    assert res.returncode == 0 and "v0001: ok" in res.stdout and "v0002: ok" in res.stdout, res.stdout + res.stderr
    out = work / "city.geojson"
    res = _cm("tiles", "export", "-f", "geojson", "-o", str(out), "--root", s3_root, "--map-version", "v1", cwd=work,
              env=s3_env)
    assert res.returncode == 0, res.stderr
    mine = tmp_path / "local.geojson"
    assert _cm("tiles", "export", "-f", "geojson", "-o", str(mine), "--root", str(local_root), "--map-version", "v1",
               cwd=work, env=s3_env).returncode == 0
    assert json.loads(out.read_text()) == json.loads(mine.read_text())
    assert sorted(p.name for p in work.iterdir()) == ["city.geojson"]  # no folder named after the root

    from mapformat.loader import open_map

    remote, here = open_map(f"{s3_root}/maps/city"), open_map(local_root / "maps" / "city")
    assert remote.manifest == here.manifest
    assert remote.all_corners().equals(here.all_corners()) and remote.all_corners().num_rows > 0
    k = remote.tile_keys()[0]
    assert (remote.tile_marking(*k) == here.tile_marking(*k)).all()
    assert open_map(f"{s3_root}/maps/city/v0001").manifest["version"] == 1


def test_a_flipped_byte_in_the_bucket_is_found_by_verify(local_root, s3_root, s3_env, tmp_path):
    store = Store.open(s3_root)
    push_map(local_root, "city", store)
    loc = storage.version_dir(storage.map_dir(store.root, "city"), 2) / "tiles" / "0_0" / "marking_mask.png"
    data = bytearray(store.read_bytes(loc))
    data[100] ^= 0xFF
    store.put_bytes(loc, bytes(data))
    res = _cm("tiles", "verify", "--root", s3_root, cwd=tmp_path, env=s3_env)
    assert res.returncode == 1 and "v0002: 1 problem(s)" in res.stdout, res.stdout + res.stderr
    assert f"{s3_root}/maps/city/v0002/tiles/0_0/marking_mask.png" in res.stdout  # named where it is: the bucket


def test_a_killed_commit_is_invisible_and_a_version_is_committed_once(local_root, s3_root, s3_env, tmp_path):
    store = Store.open(s3_root)
    mdir = storage.map_dir(store.root, "city")
    sha1 = push_version(store, mdir, local_root / "maps/city/v0001", 1)
    store.put_bytes(storage.latest_file(mdir), f"v0001 {sha1}\n".encode())
    # a writer killed after uploading v0002's files, before its manifest: every file there, no commit marker
    src = local_root / "maps/city/v0002"
    for p in sorted(src.rglob("*")):
        if p.is_file() and p.name != "manifest.json":
            store.upload_file(p, storage.version_dir(mdir, 2) / p.relative_to(src).as_posix())
    assert list_versions(store, mdir) == [1]
    res = _cm("tiles", "ls", "--root", s3_root, cwd=tmp_path, env=s3_env)
    assert res.returncode == 0 and "LATEST = v0001" in res.stdout and "v0002" not in res.stdout, res.stdout
    assert _cm("tiles", "verify", "--root", s3_root, cwd=tmp_path, env=s3_env).returncode == 0
    # gc: young leftovers are kept; old enough (--min-age-h 0) they go, the committed version stays
    res = _cm("gc", "--root", s3_root, cwd=tmp_path, env=s3_env)
    assert res.returncode == 0 and "0 other object prefix(es) to remove" in res.stdout, res.stdout + res.stderr
    res = _cm("gc", "--root", s3_root, "--min-age-h", "0", cwd=tmp_path, env=s3_env)
    assert f"would remove {s3_root}/maps/city/v0002 (uncommitted" in res.stdout, res.stdout + res.stderr
    assert list(store.walk_files(storage.version_dir(mdir, 2)))  # a dry run
    res = _cm("gc", "--root", s3_root, "--min-age-h", "0", "--apply", cwd=tmp_path, env=s3_env)
    assert res.returncode == 0 and "1 other object prefix(es) removed" in res.stdout, res.stdout + res.stderr
    assert list(store.walk_files(storage.version_dir(mdir, 2))) == [] and list_versions(store, mdir) == [1]
    assert list(store.walk_files(storage.locks_dir(store.root))) == []  # gc's own lease released
    for p in sorted(src.rglob("*")):  # killed again
        if p.is_file() and p.name != "manifest.json":
            store.upload_file(p, storage.version_dir(mdir, 2) / p.relative_to(src).as_posix())
    assert push_map(local_root, "city", store) == [2]  # the next writer commits it whole
    assert list_versions(store, mdir) == [1, 2]
    with pytest.raises(PublishConflictError, match="never overwritten"):
        push_version(store, mdir, src, 2)


def test_rollback_in_a_bucket_moves_latest_after_checking_the_version(local_root, s3_root, s3_env, tmp_path):
    store = Store.open(s3_root)
    push_map(local_root, "city", store)
    mdir = storage.map_dir(store.root, "city")
    res = _cm("tiles", "rollback", "--to", "v1", "--root", s3_root, "--map", "city", cwd=tmp_path, env=s3_env)
    assert res.returncode == 0 and "LATEST: v0002 -> v0001" in res.stdout, res.stdout + res.stderr
    v1 = store.read_bytes(storage.version_manifest(storage.version_dir(mdir, 1)))
    import hashlib

    assert store.read_bytes(storage.latest_file(mdir)) == f"v0001 {hashlib.sha256(v1).hexdigest()}\n".encode()
    loc = storage.version_dir(mdir, 2) / "tiles" / "0_0" / "corners.parquet"
    store.put_bytes(loc, store.read_bytes(loc)[:-1] + b"X")  # v0002 damaged in the bucket: refused
    res = _cm("tiles", "rollback", "--to", "v2", "--root", s3_root, "--map", "city", cwd=tmp_path, env=s3_env)
    assert res.returncode == 1 and f"{s3_root}/maps/city/v0002" in res.stderr, res.stderr
    assert store.read_bytes(storage.latest_file(mdir)).startswith(b"v0001 ")


def test_publishing_straight_to_a_bucket_continues_the_chain(local_root, s3_root, s3_env):
    store = Store.open(s3_root)
    push_map(local_root, "city", store)

    def write(staging: Path) -> dict:
        (staging / "note.txt").write_text("a third version\n")
        return {"purpose": "test"}

    pv = publish_version_to(store, "city", write)
    mdir = storage.map_dir(store.root, "city")
    assert pv.version == 3 and list_versions(store, mdir) == [1, 2, 3]
    manifest = json.loads(store.read_bytes(storage.version_manifest(storage.version_dir(mdir, 3))))
    v2 = store.read_bytes(storage.version_manifest(storage.version_dir(mdir, 2)))
    import hashlib

    assert manifest["parent_version"] == 2 and manifest["parent_manifest_sha256"] == hashlib.sha256(v2).hexdigest()
    assert store.read_bytes(storage.latest_file(mdir)).split()[0] == b"v0003"


def test_open_map_on_an_unreachable_store_raises_a_named_error(monkeypatch) -> None:
    """A localizer loading from a bucket whose endpoint is down gets ObjectStoreError naming the URI and the
    endpoint (an OSError), not the client's own exception."""
    import socket

    from mapformat.loader import open_map
    from pipeline.errors import DatasetIOError, ObjectStoreError

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{port}")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    import s3fs

    s3fs.S3FileSystem.clear_instance_cache()  # fsspec caches a file system per process: one of this test's env
    try:
        with pytest.raises(ObjectStoreError) as err:
            open_map("s3://hcmaps/root/maps/city")
    finally:
        s3fs.S3FileSystem.clear_instance_cache()  # the next test's env gets its own
    text = str(err.value)
    assert isinstance(err.value, (DatasetIOError, OSError))
    assert text.startswith("s3://hcmaps/root/maps/city: the object store") and f"127.0.0.1:{port}" in text
    assert "\n" not in text
