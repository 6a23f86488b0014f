"""Builds whose output root is on object storage (issue 58), against a real S3 API (moto's server, started by the
test session: ``tests/conftest.py::s3_env``), run as processes the way a user runs ``cornermap``.

- ``test_a_map_built_into_a_bucket_lists_verifies_exports_and_rebuilds_nothing``: a short simulated drive built
  into ``s3://BUCKET/root`` (the engine's local pool); the bucket then holds the committed datasets (each with its
  manifest) and the map, which list, verify and export (the Autoware folder, read from the version's own datasets in
  the bucket); a second build skips every stage; no local folder is named after the root.
- ``test_a_cluster_sharing_only_the_bucket_builds_the_map`` (slow): a ``tcp://`` scheduler and two separately started
  ``dask worker`` processes, each with its own ``--local-directory``, build the same kind of map into the bucket.
"""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.test_cli_process import cornermap

REPO = Path(__file__).resolve().parents[1]
ORIGIN = "37.4979,127.0276,57"  # the simulator's origin: a pinned frame (drive-scoped reuse applies)


@pytest.fixture(scope="module")
def short_drive(tmp_path_factory) -> Path:
    """A 30-scan tiny drive, and beside it the params that turn the tiles quality gates off (``PARAMS``: 30 scans
    make too short a map for them)."""
    out = tmp_path_factory.mktemp("sim")
    res = cornermap("simulate", "--preset", "tiny", "--seed", "41", "--drives", "1", "--max-scans", "30",
                    "--out", str(out), "-q", cwd=out)
    assert res.returncode == 0, res.stderr
    (out / PARAMS).write_text("tiles: {gates_enabled: false}\n")
    return out / "drive_0" / "drive.yaml"


PARAMS = "no_gates.yaml"


def build(drive: Path, root: str, cwd: Path, *more: str, timeout: float = 600, **env: str):
    return cornermap("build", "--drive", str(drive), "--map", "city", "--root", root, "--origin", ORIGIN,
                     "--params", str(drive.parents[1] / PARAMS), "-q", "--json", *more, cwd=cwd, timeout=timeout,
                     **env)


def _objects(root: str) -> list[str]:
    """Every key under ``root`` (``s3://bucket/prefix``), relative to it."""
    from pipeline.storage import Store

    store = Store.open(root)
    return [rel for rel, _ in store.walk_files(store.root)]


def _no_local_root(cwd: Path) -> None:
    assert not (cwd / "s3:").exists() and not list(cwd.glob("**/s3:*")), "a local folder named after the root"


def _check_bucket(root: str, cwd: Path, env: dict[str, str]) -> None:
    """The map in the bucket lists, verifies and exports; every committed dataset has its manifest."""
    keys = _objects(root)
    manifests = {k.rsplit("/", 1)[0] for k in keys if k.startswith("datasets/") and k.endswith("/_manifest.json")}
    data_dirs = {k.split("/data/")[0] for k in keys if k.startswith("datasets/") and "/data/" in k}
    assert data_dirs and data_dirs <= manifests, f"data without a commit marker: {sorted(data_dirs - manifests)}"
    assert any(k.startswith("datasets/scans_raw/") for k in keys)
    ls = cornermap("tiles", "ls", "--root", root, "--map", "city", cwd=cwd, **env)
    assert ls.returncode == 0 and "v0001" in ls.stdout and "LATEST = v0001" in ls.stdout, ls.stdout + ls.stderr
    ver = cornermap("tiles", "verify", "--root", root, "--map", "city", "--json", cwd=cwd, **env)
    assert ver.returncode == 0, ver.stderr
    assert [r["ok"] for r in json.loads(ver.stdout)["versions"]] == [True], ver.stdout
    out = cwd / "autoware"
    exp = cornermap("tiles", "export", "--root", root, "--map", "city", "--format", "autoware", "--out", str(out),
                    "-q", cwd=cwd, timeout=300, **env)
    assert exp.returncode == 0, exp.stderr
    pcds = list((out / "pointcloud_map").glob("*.pcd"))
    assert pcds and all(p.stat().st_size > 100 for p in pcds)
    assert (out / "lanelet2_map.osm").is_file()
    _no_local_root(cwd)


def test_a_map_built_into_a_bucket_lists_verifies_exports_and_rebuilds_nothing(s3_env, s3_root, short_drive,
                                                                                tmp_path):
    env = {**s3_env, "CORNERMAP_SCRATCH": str(tmp_path / "scratch")}
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    res = build(short_drive, s3_root, cwd, "--workers", "2", **env)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["root"] == s3_root and doc["map_version"] == "v0001"
    assert all(s["decision"] == "ran" for s in doc["stages"].values())
    _check_bucket(s3_root, cwd, env)
    # the drive was staged into the bucket (by content) and the build's tasks read it from there
    staged = [k for k in _objects(s3_root) if k.startswith("drives/") and k.endswith("/drive_0/drive.yaml")]
    assert len(staged) == 1, staged
    # evaluate reads the map from the bucket (its LATEST, verified there)
    ev = cornermap("evaluate", "--root", s3_root, "--map", "city", "--drive", str(short_drive), "--reference", "gnss",
                   "--out", str(tmp_path / "eval"), "-q", "--json", cwd=cwd, timeout=600, **env)
    assert ev.returncode in (0, 3), ev.stderr
    assert json.loads(ev.stdout)["map_version"] == "v0001" and (tmp_path / "eval" / "metrics.json").is_file()
    # the scratch copy is a cache: removed, the next run reads the bucket (and finds everything committed)
    import shutil

    shutil.rmtree(tmp_path / "scratch")
    again = build(short_drive, s3_root, cwd, **env)
    assert again.returncode == 0, again.stderr
    assert {s["decision"] for s in json.loads(again.stdout)["stages"].values()} == {"skipped"}
    # gc keeps every dataset the published version was built from
    gc = cornermap("gc", "--root", s3_root, "--min-age-h", "0", cwd=cwd, **env)
    assert gc.returncode == 0 and "0 dataset folder(s)" in gc.stdout, gc.stdout + gc.stderr
    _no_local_root(cwd)


def test_gc_on_a_bucket_removes_unreferenced_datasets_and_keeps_the_rest(s3_env, s3_root, tmp_path):
    """``cornermap gc`` on an s3:// root: a dataset a kept version was built from stays with its upstream; one
    nothing references goes (manifest first, then its objects); an uncommitted folder stays while young."""
    from pipeline.storage import Store, dataset_dir, dataset_manifest, map_dir, version_dir, version_manifest

    store = Store.open(s3_root)
    fps = {"used": "a" * 16, "upstream": "b" * 16, "orphan": "c" * 16, "young": "d" * 16}

    def dataset(name: str, fp: str, inputs: dict, committed: bool = True) -> None:
        ddir = dataset_dir(store.root, name, fp)
        store.put_bytes(ddir / "data" / "part-all-00000.parquet", b"x" * 1000)
        if committed:
            store.put_bytes(dataset_manifest(ddir), json.dumps({"dataset": name, "fingerprint": fp, "files": [],
                                                                 "inputs": inputs}).encode())

    dataset("corner_map", fps["used"], {"scans": {"dataset": "scans_raw", "fingerprint": fps["upstream"]}})
    dataset("scans_raw", fps["upstream"], {})
    dataset("scans_raw", fps["orphan"], {})
    dataset("odometry_raw", fps["young"], {}, committed=False)
    vdir = version_dir(map_dir(store.root, "city"), 1)
    store.put_bytes(version_manifest(vdir), json.dumps({"version": 1, "inputs": {
        "corner_map": {"dataset": "corner_map", "fingerprint": fps["used"]}}}).encode())
    dry = cornermap("gc", "--root", s3_root, "--min-age-h", "1", cwd=tmp_path, **s3_env)
    assert dry.returncode == 0, dry.stderr
    assert f"would remove {s3_root}/datasets/scans_raw/{fps['orphan']}" in dry.stdout, dry.stdout
    assert "1 dataset folder(s)" in dry.stdout and "3 kept" in dry.stdout, dry.stdout
    assert store.exists(dataset_dir(store.root, "scans_raw", fps["orphan"]) / "_manifest.json")  # a dry run
    res = cornermap("gc", "--root", s3_root, "--min-age-h", "1", "--apply", cwd=tmp_path, **s3_env)
    assert res.returncode == 0, res.stderr
    left = {"/".join(k.split("/")[:3]) for k in _objects(s3_root) if k.startswith("datasets/")}
    assert left == {f"datasets/corner_map/{fps['used']}", f"datasets/scans_raw/{fps['upstream']}",
                    f"datasets/odometry_raw/{fps['young']}"}, left
    _no_local_root(tmp_path)


def test_an_uncommitted_dataset_in_the_bucket_is_not_read_as_committed(s3_env, s3_root, tmp_path):
    """A dataset whose pieces and part markers are in the bucket but whose manifest is not (a writer killed before
    its commit) is not committed: the engine's view of the root says so, and a reader refuses it by name."""
    from pipeline.errors import DatasetIOError
    from pipeline.reader import StoreInputReader
    from pipeline.storage import Store, dataset_dir, part_marker
    from pipeline.store import DataRoot

    store = Store.open(s3_root)
    ddir = dataset_dir(store.root, "toy", "f" * 16)
    store.put_bytes(part_marker(ddir, "all"), json.dumps({"output": {"files": [], "artifacts": None}}).encode())
    os.environ["CORNERMAP_SCRATCH"] = str(tmp_path)
    try:
        root = DataRoot(s3_root)
        assert root.remote and root.part("toy", "f" * 16, "all") is not None
        assert root.manifest("toy", "f" * 16) is None
        reader = StoreInputReader(s3_root, {"x": ("toy", "f" * 16)}, {"x": None})
        with pytest.raises(DatasetIOError, match="no committed data under s3://"):
            reader.read("x")
        assert root.commit("toy", "f" * 16, {"files": []}) is True
        assert root.commit("toy", "f" * 16, {"files": [], "other": 1}) is False  # a conditional put: once
        assert json.loads(store.read_bytes(ddir / "_manifest.json")) == {"files": []}
    finally:
        os.environ.pop("CORNERMAP_SCRATCH", None)


def test_a_corrupt_local_copy_is_fetched_again_and_a_corrupt_object_is_refused(s3_env, s3_root, tmp_path):
    """The local copy of an object-store root is a cache checked like the root itself: a copy altered after the
    download is fetched again; an object whose bytes differ from its manifest is an IntegrityError."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.errors import IntegrityError
    from pipeline.reader import StoreInputReader
    from pipeline.storage import Store, dataset_dir
    from pipeline.store import file_sha256

    store = Store.open(s3_root)
    src = tmp_path / "a.parquet"
    pq.write_table(pa.table({"v": [1, 2, 3]}), src)
    ddir = dataset_dir(store.root, "toy", "e" * 16)
    rec = {"path": "data/part-all-00000.parquet", "rows": 3, "bytes": src.stat().st_size, "sha256": file_sha256(src)}
    store.upload_file(src, ddir / rec["path"])
    store.put_bytes(ddir / "_manifest.json", json.dumps({"fingerprint": "e" * 16, "files": [rec]}).encode())
    os.environ["CORNERMAP_SCRATCH"] = str(tmp_path / "scratch")
    try:
        schema = pa.schema([("v", pa.int64())])
        reader = StoreInputReader(s3_root, {"x": ("toy", "e" * 16)}, {"x": schema})
        assert reader.read("x")["v"].to_pylist() == [1, 2, 3]
        local = reader.root / "datasets" / "toy" / ("e" * 16) / rec["path"]
        assert local.is_file() and str(tmp_path / "scratch") in str(local)
        data = bytearray(local.read_bytes())
        data[len(data) // 2] ^= 0xFF  # the same size: only the hash can tell
        local.write_bytes(bytes(data))
        time.sleep(0.01)
        fresh = StoreInputReader(s3_root, {"x": ("toy", "e" * 16)}, {"x": schema})
        assert fresh.read("x")["v"].to_pylist() == [1, 2, 3]  # fetched again, verified
        store.put_bytes(ddir / rec["path"], bytes(data))  # the bucket's object itself altered
        local.unlink()
        with pytest.raises(IntegrityError, match="differs from its manifest"):
            StoreInputReader(s3_root, {"x": ("toy", "e" * 16)}, {"x": schema}).read("x")
    finally:
        os.environ.pop("CORNERMAP_SCRATCH", None)


def test_a_drives_committed_partition_is_reused_from_a_sibling_by_a_server_side_copy(s3_env, s3_root, tmp_path):
    """Drive-scoped reuse on a bucket: a sibling fingerprint folder whose part marker records the same scope and whose
    files are all there is found, and its files are copied within the bucket into the new folder; a sibling missing
    one of its files, or of another scope, is not."""
    from pipeline.reuse import find_committed, link_partition
    from pipeline.storage import Store, artifacts_dir, dataset_dir
    from pipeline.store import DataRoot

    store = Store.open(s3_root)
    os.environ["CORNERMAP_SCRATCH"] = str(tmp_path)
    try:
        root = DataRoot(s3_root)
        output = {"files": [{"path": "data/drive=d0/part-drive0-00000.parquet"}],
                  "artifacts": [{"path": "trajectory.txt"}]}
        for fp, scope, complete in (("1" * 16, "other", True), ("2" * 16, "s1", False), ("3" * 16, "s1", True)):
            ddir = dataset_dir(store.root, "scans_raw", fp)
            store.put_bytes(ddir / output["files"][0]["path"], f"rows of {fp}".encode())
            if complete:
                store.put_bytes(artifacts_dir(ddir, "drive0") / "trajectory.txt", f"poses of {fp}".encode())
            root.put_part("scans_raw", fp, "drive0", {"output": output, "scope": scope})
        own = "f" * 16
        hit = find_committed(root, "scans_raw", own, "drive0", "s1")
        assert hit is not None and hit[0] == "3" * 16
        assert find_committed(root, "scans_raw", own, "drive0", "nowhere") is None
        link_partition(root, "scans_raw", hit[0], own, "drive0", hit[1]["output"])
        ddir = dataset_dir(store.root, "scans_raw", own)
        assert store.read_bytes(ddir / output["files"][0]["path"]) == b"rows of " + b"3" * 16
        assert store.read_bytes(artifacts_dir(ddir, "drive0") / "trajectory.txt") == b"poses of " + b"3" * 16
        assert not list(tmp_path.rglob("*.parquet")), "a server-side copy passes no bytes through the task"
    finally:
        os.environ.pop("CORNERMAP_SCRATCH", None)


@contextlib.contextmanager
def _dask_cluster(tmp_path: Path, env: dict[str, str]):
    """A ``dask scheduler`` and two ``dask worker`` processes started apart, each worker in its own folder."""
    from fixtures.s3server import free_port

    port = free_port()
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    worker = [sys.executable, "-m", "distributed.cli.dask_worker"]
    penv = {k: v for k, v in os.environ.items() if k not in ("CORNERMAP_SCRATCH", "CORNERMAP_ROOT")}
    penv.update(env, PYTHONPATH=str(REPO))
    procs = []
    logs = []
    try:
        log = open(tmp_path / "scheduler.log", "w")
        logs.append(log)
        procs.append(subprocess.Popen(dask + ["--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                                      env=penv, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path))
        address = f"tcp://127.0.0.1:{port}"
        folders = []
        for n in range(2):
            folder = tmp_path / f"worker{n}"
            folder.mkdir()
            folders.append(folder)
            log = open(tmp_path / f"worker{n}.log", "w")
            logs.append(log)
            procs.append(subprocess.Popen(worker + [address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                                    "--local-directory", str(folder), "--host", "127.0.0.1"],
                                          env=penv, stdout=log, stderr=subprocess.STDOUT, cwd=folder))
        from distributed import Client

        deadline = time.time() + 120
        with Client(address, timeout=60) as client:
            while len(client.scheduler_info()["workers"]) < 2:
                assert time.time() < deadline, "the two workers did not join"
                time.sleep(0.5)
        yield address, folders
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        for log in logs:
            log.close()


@pytest.mark.slow
def test_a_cluster_sharing_only_the_bucket_builds_the_map(s3_env, s3_root, short_drive, tmp_path):
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    with _dask_cluster(tmp_path, s3_env) as (address, folders):
        res = build(short_drive, s3_root, client_dir, "--scheduler", address, timeout=900,
                    CORNERMAP_SCRATCH=str(client_dir / "scratch"), **s3_env)
        assert res.returncode == 0, res.stderr
        assert json.loads(res.stdout)["map_version"] == "v0001"
        # the tasks ran in the workers' own folders (their local copies of the root), not in the client's: the scans
        # were written by a worker (the client plans from manifests and reads a few small datasets to plan)
        scans = "**/cornermap-cache/*/datasets/scans_raw/*/data/**/*.parquet"
        assert any(list(f.glob(scans)) for f in folders), "no worker wrote its local copy under its folder"
        assert not list((client_dir / "scratch").glob(scans)), "the scans were written or read by the client"
        # the drive reached the workers through the bucket: staged there by the client, fetched by a worker
        assert any(list(f.glob("**/cornermap-drives/*/**/drives/*/drive_0/scans/*.pcd")) for f in folders)
    _check_bucket(s3_root, client_dir, s3_env)
    for folder in folders:
        _no_local_root(folder)
