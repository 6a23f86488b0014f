"""Drives read through the store (issue 58, item 4: "tasks read their inputs from the store, never from a client
path"), against a real S3 API (moto's server, started by the test session: ``tests/conftest.py::s3_env``).

- ``test_a_local_drive_is_staged_once_by_content_and_fetched_whole``: ``stage_drive`` uploads a drive (its survey in
  ``../survey/`` keeps its place) into ``ROOT/drives/<fp16>/`` with its marker last; staging it again uploads
  nothing; ``local_drive`` in another scratch folder fetches every file byte-identical, and the drive's fingerprint
  by URI is the same before and after; an object replaced in the bucket changes it and is fetched again.
- ``test_drive_check_reads_a_drive_in_a_bucket``: ``cornermap drive check s3://...`` as a process: exit 0 on the
  staged drive, exit 1 naming the URI of one that is not there.
- ``test_workers_build_a_drive_only_the_bucket_holds`` (slow): a ``tcp://`` scheduler and two separately started
  ``dask worker`` processes, each in its own folder; the drive is uploaded to the bucket and its local folder removed
  before the build, so only the store can give it to the tasks; the map lists, verifies and exports from the bucket,
  the workers' folders hold their fetched copies of the drive, and nothing is named after the root.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from tests.test_cli_process import cornermap
from tests.test_s3_build import PARAMS, _check_bucket, _dask_cluster, _no_local_root, _objects

ORIGIN = "37.4979,127.0276,57"


@pytest.fixture(scope="module")
def short_drive(tmp_path_factory) -> Path:
    """A 30-scan tiny drive (its survey in ``../survey/``) and beside it the params that turn the tiles quality gates
    off (30 scans make too short a map for them)."""
    out = tmp_path_factory.mktemp("sim")
    res = cornermap(
        "simulate",
        "--preset",
        "tiny",
        "--seed",
        "41",
        "--drives",
        "1",
        "--max-scans",
        "30",
        "--out",
        str(out),
        "-q",
        cwd=out,
    )
    assert res.returncode == 0, res.stderr
    (out / PARAMS).write_text("tiles: {gates_enabled: false}\n")
    return out / "drive_0" / "drive.yaml"


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_local_drive_is_staged_once_by_content_and_fetched_whole(s3_env, s3_root, short_drive, tmp_path, monkeypatch):
    from pipeline import drive_store
    from pipeline.fingerprint import drive_fingerprint
    from pipeline.storage import Store

    monkeypatch.setenv("CORNERMAP_SCRATCH", str(tmp_path / "client"))
    uri = drive_store.stage_drive(s3_root, short_drive)
    fp = drive_fingerprint(short_drive)
    assert uri == f"{s3_root}/drives/{fp[:16]}/drive_0/drive.yaml", uri
    keys = _objects(s3_root)
    staged = {k.split("/", 2)[2] for k in keys if k.startswith(f"drives/{fp[:16]}/")}
    sim = short_drive.parents[1]
    local = {rel for rel in _files(sim) if rel.startswith(("drive_0/", "survey/"))}
    assert staged == local | {"_staged.json"}, sorted(staged ^ (local | {"_staged.json"}))
    store = Store.open(s3_root)
    marker = f"drives/{fp[:16]}/_staged.json"
    files = lambda: {k: v for k, v in store.walk_objects(store.root).items() if not k.startswith("locks/")}  # noqa: E731
    before = files()
    drive_store._STAGED.clear()  # another process: only the bucket's marker says it is staged
    assert drive_store.stage_drive(s3_root, short_drive) == uri
    after = files()
    assert {k: v for k, v in after.items() if k != marker} == {k: v for k, v in before.items() if k != marker}, (
        "a staged drive was uploaded again"
    )
    assert after[marker][0] == before[marker][0] and after[marker][1] >= before[marker][1]  # the marker renewed
    # a worker's scratch: the drive fetched from the bucket, every file as the client has it
    fp_uri = drive_store.remote_drive_fingerprint(uri)
    monkeypatch.setenv("CORNERMAP_SCRATCH", str(tmp_path / "worker"))
    got = drive_store.local_drive(uri)
    assert str(got).startswith(str(tmp_path / "worker")) and got.name == "drive.yaml"
    base = got.parents[1]
    fetched = _files(base)
    assert {k: v for k, v in fetched.items() if k in local} == {k: (sim / k).read_bytes() for k in local}
    assert drive_store.remote_drive_fingerprint(uri) == fp_uri
    # an object replaced in the bucket: another fingerprint, and fetched again
    gnss = uri.rsplit("/", 1)[0] + "/gnss_inspva.csv"
    from pipeline.drive_store import _split

    bucket, key = _split(gnss)
    Store.open(bucket).put_bytes(Store.open(bucket).root / key, b"gps_week,gps_seconds\n")
    assert drive_store.remote_drive_fingerprint(uri) != fp_uri
    assert (drive_store.local_drive(uri).parent / "gnss_inspva.csv").read_bytes() == b"gps_week,gps_seconds\n"


def test_drive_check_reads_a_drive_in_a_bucket(s3_env, s3_root, short_drive, tmp_path):
    from pipeline import drive_store

    os.environ["CORNERMAP_SCRATCH"] = str(tmp_path / "stage")
    try:
        uri = drive_store.stage_drive(s3_root, short_drive)
    finally:
        os.environ.pop("CORNERMAP_SCRATCH", None)
    env = {**s3_env, "CORNERMAP_SCRATCH": str(tmp_path / "scratch")}
    ok = cornermap("drive", "check", "--placed", uri, cwd=tmp_path, **env)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert f"ok: {uri}" in ok.stdout, ok.stdout
    gone = uri.replace("/drive_0/", "/drive_9/")
    bad = cornermap("drive", "check", gone, cwd=tmp_path, **env)
    assert bad.returncode == 1 and gone in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
    _no_local_root(tmp_path)


@pytest.mark.slow
def test_workers_build_a_drive_only_the_bucket_holds(s3_env, s3_root, short_drive, tmp_path):
    from pipeline.storage import Store

    # deliver the drive (and its survey beside it) to the bucket as a user would, then remove every local copy
    sim = tmp_path / "sim"
    shutil.copytree(short_drive.parents[1], sim)
    store = Store.open(s3_root)
    bucket_drives = store.root.parent / "deliveries"
    files = [p for p in sorted(sim.rglob("*")) if p.is_file() and p.parts[len(sim.parts)] in ("drive_0", "survey")]
    store.upload_files([(p, bucket_drives / p.relative_to(sim).as_posix()) for p in files])
    params = tmp_path / PARAMS
    shutil.copy(sim / PARAMS, params)
    shutil.rmtree(sim)
    uri = f"s3://{bucket_drives.as_posix()}/drive_0/drive.yaml"
    client = tmp_path / "client"
    client.mkdir()
    with _dask_cluster(tmp_path, s3_env) as (address, folders):
        res = cornermap(
            "build",
            "--drive",
            uri,
            "--map",
            "city",
            "--root",
            s3_root,
            "--origin",
            ORIGIN,
            "--params",
            str(params),
            "-q",
            "--json",
            "--scheduler",
            address,
            cwd=client,
            timeout=900,
            CORNERMAP_SCRATCH=str(client / "scratch"),
            **s3_env,
        )
        assert res.returncode == 0, res.stderr
        doc = json.loads(res.stdout)
        assert doc["map_version"] == "v0001" and doc["stages"]["ingest"]["decision"] == "ran"
        fetched = [f for f in folders if list(f.glob("**/cornermap-drives/*/deliveries/drive_0/scans/*.pcd"))]
        assert fetched, "no worker fetched the drive into its own folder"
        assert not list((client / "scratch").glob("**/*.pcd")), "the client fetched the scans"
        rows = cornermap("tiles", "ls", "--root", s3_root, "--map", "city", cwd=client, **s3_env)
        assert rows.returncode == 0, rows.stderr
    _check_bucket(s3_root, client, s3_env)
    assert not any(k.startswith("drives/") for k in _objects(s3_root)), "a drive given by URI was staged again"
    for folder in folders:
        _no_local_root(folder)


def test_a_drive_given_only_by_uri_gets_the_clients_frame_check(s3_env, s3_root, tmp_path):
    """``cornermap build --drive s3://.../drive.yaml`` of drives nothing places in the map's frame: the client's
    check refuses them as it refuses local drives (exit 3, one line naming each drive by its URI and what to add),
    before any stage runs: nothing committed in the bucket, and the client read the drive file, its stamps and the
    names of its scans, not the scans (no scan file left in its scratch or elsewhere in its folder)."""
    import yaml

    from fixtures.ingest import write_synthetic_drive
    from pipeline.storage import Store

    local = tmp_path / "delivered"
    for name, n_scans in (("bare", 3), ("keyframes", 24)):  # 24 scans: more than a check copy fetches
        drive = write_synthetic_drive(local, name=name, n_scans=n_scans).drive_file
        doc = yaml.safe_load(drive.read_text())
        del doc["gnss"]
        doc["scan_times"] = {"source": "stamps_csv"}
        if name == "keyframes":  # a start heading alone, scans 1.5 s apart: a keyframe drive nothing checks
            doc["start"] = {"heading_deg": 30.0, "heading_convention": "azimuth_cw_from_north"}
            stamps = drive.parent / "scans" / "stamps.csv"
            lines = stamps.read_text().splitlines()
            col = lines[0].split(",").index("gps_seconds")
            rows = [ln.split(",") for ln in lines[1:]]
            for k, r in enumerate(rows):
                r[col] = f"{float(rows[0][col]) + 1.5 * k:.6f}"
            stamps.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
        drive.write_text(yaml.safe_dump(doc))
    store = Store.open(s3_root)
    base = store.root.parent / "deliveries"
    store.upload_files([(p, base / p.relative_to(local).as_posix()) for p in sorted(local.rglob("*")) if p.is_file()])
    shutil.rmtree(local)
    uris = [f"s3://{base.as_posix()}/{name}/drive.yaml" for name in ("bare", "keyframes")]
    client = tmp_path / "client"
    client.mkdir()
    res = cornermap("build", "--drive", uris[0], "--drive", uris[1], "--map", "city", "--root", s3_root, "--origin",
                    ORIGIN, "--quiet", cwd=client, CORNERMAP_SCRATCH=str(client / "scratch"), **s3_env)
    assert res.returncode == 3, (res.stdout, res.stderr)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in res.stderr, lines
    assert "drive bare: its frame cannot be fixed" in lines[0] and f"({uris[0]})" in lines[0], lines[0]
    assert "add one of: a gnss section" in lines[0], lines[0]
    assert "drive keyframes: a keyframe drive (median 1.50 s between scans)" in lines[0], lines[0]
    assert f"({uris[1]})" in lines[0] and "cornermap-check-" not in lines[0], lines[0]
    assert not [k for k in _objects(s3_root) if k.endswith("_manifest.json")], "a dataset was committed"
    assert not list(client.rglob("*.pcd")), "the client fetched scans"
    _no_local_root(client)
