"""``cornermap rebuild`` with its root and its inbox in a bucket (issue 58), against a real S3 API (moto's server,
started by the test session: ``tests/conftest.py::s3_env``), run as processes where exit codes matter.

- ``test_two_nights_on_a_bucket``: ``maps create`` in ``s3://BUCKET/root``; night 1 a drive delivered to
  ``s3://BUCKET/inbox/drive_0/`` with a READY object -> v0001; night 2 a second drive and a corrupt one -> the corrupt
  one's objects move to ``inbox/quarantine/`` with a reason, v0002 is published by an incremental rebuild (the old
  drive's poses held: its trajectory's bytes identical in v0001 and v0002), LATEST moves, the gate's record is in the
  bucket; a third run has nothing to do; the versions verify from the bucket; no folder named after the root.
- ``test_a_lease_held_on_the_bucket_is_exit_75``: another holder of the map's lease -> exit 75, one line, nothing
  written.
- ``test_a_drive_still_arriving_waits_and_one_naming_files_outside_the_inbox_is_quarantined``: the delivery protocol
  on a bucket (READY older than an object, no READY within the quiet period, a path leaving the inbox).
- ``test_killed_rebuilds_on_a_bucket_leave_latest_complete`` (slow): rebuilds SIGKILLed at random points; LATEST
  always names a complete version that verifies from the bucket; the next run completes.
- ``test_local_copies_are_pruned_to_the_cap_and_a_copy_in_use_is_kept``: the LRU of the local copies.
"""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.test_cli_process import cornermap

REPO = Path(__file__).resolve().parents[1]
ORIGIN = "37.4979,127.0276,57"


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """Two short tiny drives (seed 41, 40 scans) and the params that turn the tiles quality gates off (too short a
    map for them)."""
    out = tmp_path_factory.mktemp("sim")
    res = cornermap("simulate", "--preset", "tiny", "--seed", "41", "--drives", "2", "--max-scans", "40",
                    "--out", str(out), "-q", cwd=out, timeout=600)
    assert res.returncode == 0, res.stderr
    (out / "no_gates.yaml").write_text("tiles: {gates_enabled: false}\n")
    return out


def deliver(inbox: str, local: Path, name: str, ready: bool = True) -> None:
    """Upload the folder ``local`` to ``INBOX/name/`` (as a delivery tool would), then its READY object."""
    from pipeline.storage import Store

    store = Store.open(inbox)
    for p in sorted(local.rglob("*")):
        if p.is_file():
            store.upload_file(p, store.root / name / p.relative_to(local).as_posix())
    if ready:
        time.sleep(1.1)  # S3 stamps are whole seconds: READY after the last object
        store.put_bytes(store.root / name / "READY", b"")


def keys(uri: str) -> list[str]:
    from pipeline.storage import Store

    store = Store.open(uri)
    return [rel for rel, _ in store.walk_files(store.root)]


def rebuild_args(root: str, inbox: str, sim: Path, *more: str) -> tuple[str, ...]:
    return ("rebuild", "--root", root, "--map", "city", "--inbox", inbox, "--min-free-gib", "0.1", "--params",
            str(sim / "no_gates.yaml"), "-q", *more)


@pytest.mark.slow
def test_two_nights_on_a_bucket(s3_env, s3_root, sim, tmp_path):
    from pipeline.storage import Store

    bucket = s3_root.rsplit("/", 1)[0]
    inbox = f"{bucket}/inbox"
    env = {**s3_env, "CORNERMAP_SCRATCH": str(tmp_path / "scratch")}
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    res = cornermap("maps", "create", "--root", s3_root, "--map", "city", "--origin", ORIGIN, cwd=cwd, **env)
    assert res.returncode == 0 and f"{s3_root}/maps/city/map.json" in res.stdout, res.stderr
    deliver(inbox, sim / "survey", "survey", ready=False)
    deliver(inbox, sim / "drive_0", "drive_0")

    night1 = cornermap(*rebuild_args(s3_root, inbox, sim), cwd=cwd, timeout=900, **env)
    assert night1.returncode == 0 and "published map 'city' v0001" in night1.stdout, night1.stdout + night1.stderr

    deliver(inbox, sim / "drive_1", "drive_1")
    deliver(inbox, sim / "drive_1", "drive_bad", ready=False)
    store = Store.open(inbox)
    store.put_bytes(store.root / "drive_bad" / "gnss_inspva.csv", b"latitude_deg\nnot,a,gnss,row\n")
    time.sleep(1.1)
    store.put_bytes(store.root / "drive_bad" / "READY", b"")
    night2 = cornermap(*rebuild_args(s3_root, inbox, sim), cwd=cwd, timeout=900, **env)
    assert night2.returncode == 0, night2.stdout + night2.stderr
    assert f"quarantined drive_bad -> {inbox}/quarantine/drive_bad" in night2.stdout, night2.stdout
    assert "published map 'city' v0002 (LATEST): 2 drive(s), added drive_1" in night2.stdout, night2.stdout
    assert "gate: ekf.rms_2d_m" in night2.stdout  # the regression gate ran (on a snapshot of both versions)
    have = keys(bucket)
    assert "inbox/quarantine/drive_bad/drive.yaml" in have and not any(k.startswith("inbox/drive_bad/") for k in have)
    reason = store.read_bytes(store.root / "quarantine" / "drive_bad.reason.txt").decode()
    assert "drive check" in reason and "gnss_inspva.csv" in reason, reason
    # the reason's hint runs as written: `cornermap drive check` reads the quarantined drive from the bucket
    hint = reason.split("run `cornermap ", 1)[1].split("`", 1)[0].split()
    assert hint[:2] == ["drive", "check"] and hint[-1] == f"{inbox}/quarantine/drive_bad/drive.yaml", reason
    checked = cornermap(*hint, cwd=cwd, **env)
    assert checked.returncode == 1 and hint[-1] in checked.stderr, checked.stdout + checked.stderr
    assert str(tmp_path / "scratch") not in checked.stderr + checked.stdout, checked.stderr  # the bucket's names
    root = Store.open(s3_root)
    assert root.read_bytes(root.root / "maps/city/LATEST").decode().startswith("v0002 ")
    gate = json.loads(root.read_bytes(root.root / "maps/city/gate/v0002.json"))
    assert gate["ok"] and gate["previous"] == 1 and gate["candidate"] == 2
    ident = json.loads(root.read_bytes(root.root / "maps/city/map.json"))
    assert [(d["name"], d["path"], d["added_in"]) for d in ident["drives"]] == [
        ("drive_0", f"{inbox}/drive_0/drive.yaml", 1), ("drive_1", f"{inbox}/drive_1/drive.yaml", 2)]
    # incremental: the untouched old drive's published trajectory is v0001's byte for byte
    t1, t2 = (root.read_bytes(root.root / f"maps/city/v000{k}/trajectories/drive_0.tum") for k in (1, 2))
    assert t1 == t2 and len(t1) > 100
    manifest = json.loads(root.read_bytes(root.root / "maps/city/v0002/manifest.json"))
    assert sorted(d["drive"] for d in manifest["source_drives"]) == ["drive_0", "drive_1"]

    again = cornermap(*rebuild_args(s3_root, inbox, sim), cwd=cwd, timeout=600, **env)
    assert again.returncode == 0 and again.stdout.startswith("nothing to do") and "LATEST v0002" in again.stdout, \
        again.stdout + again.stderr
    # maps show reads the drives' files and the pose graph's drift through the store
    show = cornermap("maps", "show", "--root", s3_root, "--map", "city", "--json", cwd=cwd, **env)
    assert show.returncode == 0, show.stderr
    shown = json.loads(show.stdout)
    assert [(r["name"], r["first"][-3:], r["last"][-3:]) for r in shown["drives"]] == [
        ("drive_0", "GPS", "GPS"), ("drive_1", "GPS", "GPS")], shown["drives"]
    assert shown["drift"] is not None and shown["drift"]["version"] == "v0002", shown["drift"]
    ver = cornermap("tiles", "verify", "--root", s3_root, "--map", "city", "--all", "--json", cwd=cwd, **env)
    assert ver.returncode == 0 and [r["ok"] for r in json.loads(ver.stdout)["versions"]] == [True, True], ver.stdout
    assert not (cwd / "s3:").exists() and not list(cwd.glob("**/s3:*")), "a local folder named after the root"


def test_a_lease_held_on_the_bucket_is_exit_75(s3_env, s3_root, sim, tmp_path):
    from mapservice.maps import create_map
    from pipeline.leases import LeaseLocks
    from pipeline.locks import map_key
    from pipeline.storage import Store

    bucket = s3_root.rsplit("/", 1)[0]
    create_map(s3_root, "city", {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0})
    deliver(f"{bucket}/inbox", sim / "drive_0", "drive_0")
    before = sorted(keys(bucket))
    store = Store.open(s3_root)
    with LeaseLocks(store, holder="another-rebuild").hold(map_key("city"), exclusive=True, what="another rebuild"):
        res = cornermap(*rebuild_args(s3_root, f"{bucket}/inbox", sim), cwd=tmp_path, **s3_env,
                        CORNERMAP_SCRATCH=str(tmp_path / "scratch"))
        assert res.returncode == 75, res.stdout + res.stderr
        assert res.stdout == "" and len(res.stderr.strip().splitlines()) == 1 and "another rebuild" in res.stderr
    lock_free = [k for k in keys(bucket) if "/locks/" not in f"/{k}"]
    assert lock_free == [k for k in before if "/locks/" not in f"/{k}"], "the refused rebuild wrote to the bucket"


def test_a_drive_still_arriving_waits_and_one_naming_files_outside_the_inbox_is_quarantined(s3_env, s3_root, sim,
                                                                                            tmp_path, monkeypatch):
    from mapservice.inbox import StoreInbox
    from pipeline.storage import SCRATCH_ENV, Store

    monkeypatch.setenv(SCRATCH_ENV, str(tmp_path / "scratch"))  # the inbox's local copy

    bucket = s3_root.rsplit("/", 1)[0]
    inbox = f"{bucket}/inbox"
    store = Store.open(inbox)
    yaml_text = (sim / "drive_0" / "drive.yaml").read_text()
    store.put_bytes(store.root / "late" / "drive.yaml", yaml_text.encode())
    store.put_bytes(store.root / "late" / "READY", b"")
    time.sleep(3.1)  # beyond the protocol's clock slack (2 s)
    store.put_bytes(store.root / "late" / "gnss_inspva.csv", b"arrived after READY\n")
    store.put_bytes(store.root / "quiet" / "drive.yaml", yaml_text.encode())
    store.put_bytes(store.root / "escape" / "drive.yaml",
                    yaml_text.replace("../survey/survey.las", "../../root/maps/city/map.json").encode())
    box = StoreInbox(inbox)
    found, refused = box.scan()
    by_name = {d.name: d for d in found}
    assert sorted(by_name) == ["escape", "late", "quiet"] and refused == []
    assert "s after its READY marker" in box.waiting_reason(by_name["late"], 600.0)
    assert "taken after 10 min without a change" in box.waiting_reason(by_name["quiet"], 600.0)
    assert box.waiting_reason(by_name["quiet"], 0.0) is None
    assert box.containment_problem(by_name["quiet"]) is None
    assert "outside the inbox" in box.containment_problem(by_name["escape"])
    dst = box.quarantine(by_name["escape"].entry, "a test reason")
    assert dst == f"{inbox}/quarantine/escape"
    have = keys(inbox)
    assert "quarantine/escape/drive.yaml" in have and "quarantine/escape.reason.txt" in have
    assert not any(k.startswith("escape/") for k in have)


@pytest.mark.slow
def test_killed_rebuilds_on_a_bucket_leave_latest_complete(s3_env, s3_root, sim, tmp_path):
    """SIGKILL at random points of a rebuild (the build, the commit of the version's objects, the gate); a short
    lease (2 s) so that the next run takes over the dead holder's lock."""
    from pipeline.storage import Store

    bucket = s3_root.rsplit("/", 1)[0]
    inbox = f"{bucket}/inbox"
    env = {**s3_env, "CORNERMAP_SCRATCH": str(tmp_path / "scratch"), "CORNERMAP_LEASE_TTL_S": "2"}
    cwd = tmp_path
    assert cornermap("maps", "create", "--root", s3_root, "--map", "city", "--origin", ORIGIN, cwd=cwd,
                     **env).returncode == 0
    deliver(inbox, sim / "survey", "survey", ready=False)
    deliver(inbox, sim / "drive_0", "drive_0")
    args = rebuild_args(s3_root, inbox, sim)
    first = cornermap(*args, cwd=cwd, timeout=900, **env)
    assert first.returncode == 0, first.stdout + first.stderr
    deliver(inbox, sim / "drive_1", "drive_1")

    def latest_verifies() -> int:
        root = Store.open(s3_root)
        line = root.read_bytes(root.root / "maps/city/LATEST").decode()
        ver = cornermap("tiles", "verify", "--root", s3_root, "--map", "city", "--json", cwd=cwd, **env)
        assert ver.returncode == 0, ver.stdout + ver.stderr
        return int(line.split()[0][1:])

    rng = random.Random(58)
    for _ in range(3):
        p = subprocess.Popen([sys.executable, "-m", "mapservice", *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, env={**os.environ, **env, "PYTHONPATH": str(REPO)}, cwd=cwd,
                             start_new_session=True)
        time.sleep(rng.uniform(5.0, 45.0))
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        assert latest_verifies() in (1, 2)
        time.sleep(2.5)  # the dead holder's lease expires
    res = cornermap(*args, cwd=cwd, timeout=900, **env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert latest_verifies() == 2
    assert "published map 'city' v0002" in res.stdout or res.stdout.startswith("nothing to do"), res.stdout


def test_local_copies_are_pruned_to_the_cap_and_a_copy_in_use_is_kept(tmp_path, monkeypatch):
    """Files least recently read go first; a copy another process marks as in use is never touched; a copy left
    empty goes whole."""
    from pipeline import storage
    from pipeline.store import prune_local_copies

    monkeypatch.setenv(storage.SCRATCH_ENV, str(tmp_path))
    cache = tmp_path / storage.CACHE
    idle, busy = cache / "idle", cache / "busy"
    for folder in (idle, busy):
        (folder / "data").mkdir(parents=True)
    now = time.time()
    for k, age in enumerate((300, 200, 100)):  # older reads first
        f = idle / "data" / f"f{k}.bin"
        f.write_bytes(b"x" * 1000)
        os.utime(f, (now - age, now - age))
    (busy / "data" / "b.bin").write_bytes(b"y" * 5000)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; sys.path.insert(0, sys.argv[1]); from pathlib import Path; "
        "from pipeline.store import use_local_copy; use_local_copy(Path(sys.argv[2])); print('held', flush=True); "
        "time.sleep(60)"), str(REPO), str(busy)], stdout=subprocess.PIPE, text=True,
        env={**os.environ, storage.SCRATCH_ENV: str(tmp_path)})
    try:
        assert holder.stdout.readline().strip() == "held"
        removed, left = prune_local_copies(cap_bytes=6500)  # 8000 bytes: the two oldest idle files go
        assert removed == 2 and left == 6000
        assert sorted(p.name for p in (idle / "data").iterdir()) == ["f2.bin"]
        removed, left = prune_local_copies(cap_bytes=0)
        assert removed == 1 and left == 5000 and not idle.exists() and (busy / "data" / "b.bin").is_file()
    finally:
        holder.kill()
        holder.wait()
    assert prune_local_copies(cap_bytes=0) == (1, 0) and not busy.exists()
