"""``cornermap gc`` on staged drives (``ROOT/drives/<fp16>/``: local drives a build uploaded into an object-store
root), the same test on a local folder and on S3 (moto's server, ``tests/conftest.py::s3_env``).

A staged drive that a kept dataset's manifest names (its ``drives``) or that a map's identity names (here its check
drive) stays; one nothing names goes once its marker is older than ``--min-age-h``, one staged more recently stays
(a build that staged it has not started its run yet); a dry run deletes nothing and ``--json`` says all of it; while
anyone stages a drive (the root's lock shared) ``gc --apply`` exits 75 and deletes nothing.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from tests.test_cli_process import cornermap


@pytest.fixture(params=["local", "s3"])
def root(request, tmp_path) -> str:
    if request.param == "local":
        return str(tmp_path / "root")
    return request.getfixturevalue("s3_root")


def _env(root: str, request) -> dict:
    return request.getfixturevalue("s3_env") if root.startswith("s3://") else {}


def _marker_age_s(store, fp16: str) -> float:
    from pipeline import storage

    return time.time() - store.walk_objects(storage.staged_drive_dir(store.root, fp16))[storage.STAGED_MARKER][1]


def test_gc_removes_staged_drives_nothing_live_names(root, tmp_path, request, monkeypatch):
    from fixtures.ingest import write_synthetic_drive
    from mapservice import gc
    from mapservice.maps import CheckDrive, create_map
    from pipeline import drive_store, storage
    from pipeline.locks import ROOT_KEY, locks_for
    from pipeline.storage import Store

    env = _env(root, request)
    monkeypatch.setenv("CORNERMAP_SCRATCH", str(tmp_path / "scratch"))
    store = Store.open(root)
    staged = {}
    for seed, name in enumerate(("used", "checked", "orphan", "young")):
        drive = write_synthetic_drive(tmp_path / "drives", name=name, n_scans=2, seed=seed).drive_file
        if name == "young":  # staged later than the others: the threshold below falls between the two
            time.sleep(3.0)
        staged[name] = drive_store.stage_drive(root, drive)
    fp = {name: uri.split("/drives/", 1)[1].split("/", 1)[0] for name, uri in staged.items()}
    assert len(set(fp.values())) == 4 and all(len(v) == 16 for v in fp.values())
    # a committed dataset whose manifest names "used", kept by a map version built from it
    ddir = storage.dataset_dir(store.root, "scans_raw", "a" * 16)
    store.put_bytes(
        storage.dataset_manifest(ddir),
        json.dumps(
            {
                "dataset": "scans_raw",
                "fingerprint": "a" * 16,
                "files": [],
                "inputs": {},
                "drives": {"used": str(Path(staged["used"]))},
            }
        ).encode(),
    )  # as the engine records it (a Path's str)
    mdir = storage.map_dir(store.root, "city")
    store.put_bytes(
        storage.version_manifest(storage.version_dir(mdir, 1)),
        json.dumps({"version": 1, "inputs": {"scans_raw": {"dataset": "scans_raw", "fingerprint": "a" * 16}}}).encode(),
    )
    create_map(
        root, "city", {"lat_deg": 37.5, "lon_deg": 127.0, "h_m": 50.0}, check_drive=CheckDrive(path=staged["checked"])
    )  # the map's identity names "checked"
    kept_objects = {
        name: store.walk_objects(storage.staged_drive_dir(store.root, fp[name]))
        for name in ("used", "checked", "young")
    }
    orphan = storage.staged_drive_dir(store.root, fp["orphan"])
    last = lambda items: sorted(str(i).rstrip("/").rsplit("/", 1)[-1] for i in items)  # noqa: E731

    # as a process, --min-age-h 0: every staged drive nothing names would go; a dry run deletes nothing
    dry = cornermap("gc", "--root", root, "--min-age-h", "0", "--json", cwd=tmp_path, **env)
    assert dry.returncode == 0, dry.stderr
    doc = json.loads(dry.stdout)
    assert last(doc["drives"]["remove"]) == sorted([fp["orphan"], fp["young"]]), doc["drives"]
    assert last(doc["drives"]["kept"]) == sorted([fp["used"], fp["checked"]]), doc["drives"]
    assert doc["drives"]["remove_bytes"] > 0 and doc["applied"] is False and doc["drives"]["young"] == []
    assert doc["datasets"]["remove"] == [] and doc["datasets"]["kept"] == 1, doc["datasets"]
    text = cornermap("gc", "--root", root, "--min-age-h", "0", cwd=tmp_path, **env)
    assert text.returncode == 0 and "(a staged drive nothing kept names)" in text.stdout, text.stdout
    assert "2 staged drive(s)" in text.stdout, text.stdout
    assert store.exists(storage.staged_marker(orphan)), "a dry run deleted"
    # while a build stages a drive (the root's lock shared): exit 75, nothing deleted
    with locks_for(store).hold(ROOT_KEY, exclusive=False, what="a build staging a drive"):
        locked = cornermap("gc", "--root", root, "--min-age-h", "0", "--apply", cwd=tmp_path, **env)
    assert locked.returncode == 75, (locked.stdout, locked.stderr)
    assert store.exists(storage.staged_marker(orphan)), "gc deleted while the root's lock was held"

    # the grace period, judged at a stated time: "young" staged 1 s before it, "orphan" more than 3 s before
    stamps = {name: time.time() - _marker_age_s(store, fp[name]) for name in ("orphan", "young")}
    assert stamps["young"] - stamps["orphan"] > 2.0, stamps
    at_s, min_age_h = stamps["young"] + 1.0, 2.0 / 3600
    plan, apply = (gc.plan_gc, gc.apply_gc) if store.local else (gc.plan_gc_store, gc.apply_gc_store)
    planned = plan(root if store.local else store, min_age_h, now=at_s)
    assert last(planned.drives_remove) == [fp["orphan"]] and last(planned.drives_young) == [fp["young"]]
    assert last(planned.drives_keep) == sorted([fp["used"], fp["checked"]]) and planned.drives_bytes > 0
    done = apply(root if store.local else store, planned, min_age_h, at_s=at_s)
    assert last(done.drives_remove) == [fp["orphan"]]
    assert store.walk_objects(orphan) == {}, "the orphan drive's objects stayed"
    for name, objects in kept_objects.items():
        assert store.walk_objects(storage.staged_drive_dir(store.root, fp[name])) == objects, name
    # staging the removed drive again uploads it whole, and a drive found staged has its marker renewed
    drive_store._STAGED.clear()
    again = drive_store.stage_drive(root, tmp_path / "drives" / "orphan" / "drive.yaml")
    assert again == staged["orphan"] and store.exists(storage.staged_marker(orphan))
    before = _marker_age_s(store, fp["used"])
    time.sleep(1.1)
    drive_store.stage_drive(root, tmp_path / "drives" / "used" / "drive.yaml")
    assert _marker_age_s(store, fp["used"]) < before
