"""Map identity, whole-run lock, free-disk check, rollback and the gate's comparison (fast: no build)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapservice.gate import compare
from mapservice.maps import check_free_disk, create_map, pinned_frame, read_identity, run_lock
from pipeline.errors import ChecksumError, ConfigError, DatasetIOError, RunLockedError, UnknownNameError
from pipeline.versioned import publish_version, read_latest
from pipeline.versioned import rollback_latest as rollback

ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}
REPO = Path(__file__).resolve().parents[2]


def cornermap(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "mapservice", *args], capture_output=True, text=True, env=env,
                          cwd=cwd)


def _publish(mdir: Path, payload: bytes, origin: dict = ORIGIN, move_latest: bool = True):
    def write(staging: Path) -> dict:
        (staging / "tile.bin").write_bytes(payload)
        return {"enu_origin": origin, "source_drives": []}

    return publish_version(mdir, write, durable=False, move_latest=move_latest)


def test_create_writes_a_schemad_identity_and_refuses_a_second(tmp_path):
    ident = create_map(tmp_path, "city", ORIGIN, 50.0)
    doc = json.loads((tmp_path / "maps/city/map.json").read_text())
    assert doc["schema"] == "cornermap.map-identity/1" and doc["enu_origin"] == ORIGIN and doc["tile_size_m"] == 50.0
    assert read_identity(tmp_path / "maps/city") == ident and ident.drives == []
    with pytest.raises(ConfigError, match="never changed"):
        create_map(tmp_path, "city", ORIGIN)
    (tmp_path / "maps/city/map.json").write_text(json.dumps({**doc, "tile_size_m": -1}))
    with pytest.raises(ConfigError, match="tile_size_m"):
        read_identity(tmp_path / "maps/city")


def test_pinned_origin_is_used_and_another_is_refused(tmp_path):
    assert pinned_frame(tmp_path, "city", None) == (None, None)  # a new, unpinned map: the drive's origin
    create_map(tmp_path, "city", ORIGIN, 50.0)
    assert pinned_frame(tmp_path, "city", None) == (ORIGIN, 50.0)
    assert pinned_frame(tmp_path, "city", dict(ORIGIN))[0] == ORIGIN
    moved = {**ORIGIN, "lat_deg": ORIGIN["lat_deg"] + 3.4e-4}  # ~38 m north: the issue's moved frame
    with pytest.raises(ConfigError, match="would move its frame"):
        pinned_frame(tmp_path, "city", moved)


def test_unpinned_map_with_versions_keeps_latest_frame(tmp_path):
    _publish(tmp_path / "maps/old", b"a")
    assert pinned_frame(tmp_path, "old", None)[0] == ORIGIN
    with pytest.raises(ConfigError, match="LATEST"):
        pinned_frame(tmp_path, "old", {**ORIGIN, "h_m": 40.0})
    with pytest.raises(ConfigError, match="published versions are in the frame"):
        create_map(tmp_path, "old", {**ORIGIN, "lon_deg": 127.1})


def test_build_cli_refuses_another_origin_in_one_line(tmp_path):
    create_map(tmp_path, "city", ORIGIN)
    drive = tmp_path / "drive.yaml"
    drive.write_text("name: d\n")
    res = cornermap("build", "--drive", str(drive), "--map", "city", "--root", str(tmp_path),
                    "--origin", "37.5,127.0276,57")
    assert res.returncode == 1 and "would move its frame" in res.stderr and len(res.stderr.splitlines()) == 1
    assert not (tmp_path / "workflows").exists()


def test_maps_cli_create_and_show(tmp_path):
    res = cornermap("maps", "create", "--root", str(tmp_path), "--map", "city", "--origin", "37.4979,127.0276,57")
    assert res.returncode == 0, res.stderr
    res = cornermap("maps", "show", "--root", str(tmp_path), "--map", "city")
    assert res.returncode == 0 and "origin 37.4979,127.0276,57.0" in res.stdout and "no drives yet" in res.stdout
    res = cornermap("maps", "create", "--root", str(tmp_path), "--map", "../x", "--origin", "37.4979,127.0276,57")
    assert res.returncode == 2 and "not allowed" in res.stderr  # a usage error: the option's value


def test_lock_held_second_run_exits_75_and_names_the_holder(tmp_path):
    create_map(tmp_path, "city", ORIGIN)
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    mdir = tmp_path / "maps/city"
    before = sorted(p.name for p in mdir.rglob("*"))
    with run_lock(mdir):
        with run_lock(mdir):  # the holder itself may take it again (a rebuild runs its build in process)
            pass
        res = cornermap("rebuild", "--root", str(tmp_path), "--map", "city", "--inbox", str(inbox))
        assert res.returncode == 75, res.stderr
        assert f"held by pid={os.getpid()}" in res.stderr and len(res.stderr.splitlines()) == 1
    assert sorted(p.name for p in mdir.rglob("*")) == before and list(inbox.iterdir()) == []
    with run_lock(mdir):  # released: taken again
        pass


def test_lock_is_released_when_its_holder_is_killed(tmp_path):
    create_map(tmp_path, "city", ORIGIN)
    code = ("import sys, time; sys.path.insert(0, sys.argv[2]); from mapservice.maps import run_lock; "
            "from pathlib import Path\nwith run_lock(Path(sys.argv[1])):\n print('held', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "maps/city"), str(REPO)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(RunLockedError, match=f"pid={proc.pid}"):
            with run_lock(tmp_path / "maps/city"):
                pass
    finally:
        proc.kill()
        proc.wait()
    with run_lock(tmp_path / "maps/city"):
        pass


def test_rebuild_nothing_to_do_writes_nothing(tmp_path):
    create_map(tmp_path, "city", ORIGIN)
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    (inbox / "notes").mkdir()  # a folder without drive.yaml is not a drive
    def snapshot():  # but the lock files (ROOT/locks/)
        return sorted(str(p) for p in tmp_path.rglob("*") if "locks" not in p.relative_to(tmp_path).parts)

    before = snapshot()
    res = cornermap("rebuild", "--root", str(tmp_path), "--map", "city", "--inbox", str(inbox))
    assert res.returncode == 0 and res.stdout.startswith("nothing to do") and len(res.stdout.splitlines()) == 1
    assert snapshot() == before


def test_rebuild_of_a_map_without_identity_is_an_error(tmp_path):
    res = cornermap("rebuild", "--root", str(tmp_path), "--map", "city", "--inbox", str(tmp_path))
    assert res.returncode == 1 and "maps create" in res.stderr


def test_free_disk_check_gives_the_numbers(tmp_path):
    check_free_disk(tmp_path, 0.0)
    with pytest.raises(DatasetIOError, match=r"GiB free, 1000000\.00 GiB required"):
        check_free_disk(tmp_path / "not" / "yet", 1e6)


def test_rollback_writes_latest_and_deletes_nothing(tmp_path):
    mdir = tmp_path / "maps/city"
    for payload in (b"one", b"two", b"three"):
        _publish(mdir, payload)
    assert read_latest(mdir) == 3
    assert rollback(mdir, "v0001") == (3, 1)
    assert read_latest(mdir) == 1 and sorted(p.name for p in mdir.glob("v*")) == ["v0001", "v0002", "v0003"]
    from pipeline.versioned import verify_version

    assert verify_version(mdir / "v0001") == []
    with pytest.raises(UnknownNameError, match="have v0001, v0002, v0003"):
        rollback(mdir, "v0009")
    (mdir / "v0002" / "tile.bin").write_bytes(b"tampered")
    with pytest.raises(ChecksumError):
        rollback(mdir, "2")
    assert read_latest(mdir) == 1
    res = cornermap("tiles", "rollback", "--to", "v0003", "--map", "city", "--root", str(tmp_path))
    assert res.returncode == 0 and "v0001 -> v0003" in res.stdout and read_latest(mdir) == 3


def test_held_candidate_is_complete_but_not_latest(tmp_path):
    mdir = tmp_path / "maps/city"
    _publish(mdir, b"one")
    cand = _publish(mdir, b"two", move_latest=False)
    assert cand.version == 2 and read_latest(mdir) == 1 and (mdir / "v0002/manifest.json").is_file()
    assert _publish(mdir, b"three").manifest["parent_version"] == 1  # a refused candidate is not a parent


def _metrics(ekf_rms, mcl_rms=0.1, p95=0.3):
    return {"methods": {"ekf": {"rms_2d_m": ekf_rms, "p95_2d_m": p95}, "mcl": {"rms_2d_m": mcl_rms, "p95_2d_m": p95}}}


def test_gate_comparison():
    assert compare(_metrics(0.10), _metrics(0.10), 0.05, 0.2).ok
    assert compare(_metrics(0.149), _metrics(0.10), 0.05, 0.2).ok  # within 5 cm
    v = compare(_metrics(0.16), _metrics(0.10), 0.05, 0.2)
    assert not v.ok and any("ekf.rms_2d_m" in line and "worse" in line for line in v.table)
    assert compare(_metrics(1.15), _metrics(1.0), 0.05, 0.2).ok  # within 20 %
    assert not compare(None, _metrics(0.1), 0.05, 0.2).ok  # no coverage on the candidate
    assert compare(_metrics(0.3), None, 0.05, 0.2).ok  # nothing to compare


def _dataset(root: Path, ds: str, fp: str, inputs: dict, payload: bytes | None = b"x" * 1000,
             committed: bool = True) -> Path:
    d = root / "datasets" / ds / fp
    (d / "data").mkdir(parents=True)
    if payload is not None:
        (d / "data" / "part.parquet").write_bytes(payload)
    if committed:
        (d / "_manifest.json").write_text(json.dumps(
            {"dataset": ds, "fingerprint": fp, "files": [],
             "inputs": {k: {"dataset": k, "fingerprint": v} for k, v in inputs.items()}}))
    return d


def test_gc_keeps_what_kept_versions_reference_and_counts_links_once(tmp_path):
    from mapservice.gc import apply_gc, plan_gc

    scans = _dataset(tmp_path, "scans_raw", "a" * 16, {})
    corners = _dataset(tmp_path, "corner_map", "b" * 16, {"scans": "a" * 16})
    report = _dataset(tmp_path, "eval_report", "e" * 16, {"map": "b" * 16})  # downstream of a kept dataset
    old_scans = _dataset(tmp_path, "scans_raw", "c" * 16, {}, payload=None)
    os.link(scans / "data/part.parquet", old_scans / "data/part.parquet")  # linked by drive-scoped reuse
    orphan = _dataset(tmp_path, "corner_map", "d" * 16, {"scans": "c" * 16}, payload=b"y" * 500)
    running = _dataset(tmp_path, "corner_map", "f" * 16, {}, committed=False)
    killed = _dataset(tmp_path, "corner_map", "0" * 16, {}, committed=False)
    os.utime(killed, (0, 0))

    def write(staging: Path) -> dict:
        (staging / "t").write_bytes(b"t")
        return {"inputs": {"corner_map": {"dataset": "corner_map", "fingerprint": "b" * 64}}}

    publish_version(tmp_path / "maps/city", write, durable=False)
    plan = plan_gc(tmp_path, min_age_h=24)
    assert sorted(plan.keep) == sorted([scans, corners, report])
    assert sorted(plan.remove) == sorted([old_scans, orphan, killed]) and plan.young_uncommitted == [running]
    on_disk = sum(p.stat().st_size for d in plan.remove for p in d.rglob("*") if p.is_file())
    assert plan.remove_bytes == on_disk - 1000  # the linked scans stay alive in the kept folder
    res = cornermap("gc", "--root", str(tmp_path))
    assert res.returncode == 0 and "3 dataset folder(s), 0.0 MiB to free; 3 kept" in res.stdout
    assert old_scans.exists()  # a dry run deletes nothing
    apply_gc(tmp_path, plan)
    assert not old_scans.exists() and not orphan.exists() and not killed.exists()
    assert scans.exists() and (scans / "data/part.parquet").read_bytes() == b"x" * 1000 and running.exists()


def test_gc_refuses_a_folder_that_is_no_output_root(tmp_path):
    """A mistyped --root must not report "nothing to free" and exit 0 (a scheduled gc would never notice)."""
    (tmp_path / "notes").mkdir()
    for root in (tmp_path / "typo", tmp_path):
        res = cornermap("gc", "--root", str(root))
        assert res.returncode == 1 and "--root" in res.stderr and "not an output root" in res.stderr
        assert "Traceback" not in res.stderr
    (tmp_path / "maps").mkdir()  # a root made by `cornermap maps create`, nothing built yet
    assert cornermap("gc", "--root", str(tmp_path)).returncode == 0


def test_gc_keeps_the_dataset_a_kept_one_read_by_path(tmp_path):
    """The simulator's drives are read by the ingest through drive.yaml paths, not as a manifest input: a kept
    scans dataset keeps them (and a reference trajectory's folder), an unreferenced raw drive folder goes."""
    from mapservice.gc import plan_gc

    raw = _dataset(tmp_path, "raw_drives", "7" * 16, {})
    (raw / "artifacts/all/drive_0").mkdir(parents=True)
    (raw / "artifacts/all/drive_0/drive.yaml").write_text("name: drive_0\n")
    truth = _dataset(tmp_path, "truth_tracks", "8" * 16, {})
    old_raw = _dataset(tmp_path, "raw_drives", "9" * 16, {})
    scans = _dataset(tmp_path, "scans_raw", "a" * 16, {})
    doc = json.loads((scans / "_manifest.json").read_text())
    doc["drives"] = {"drive_0": str(raw / "artifacts/all/drive_0/drive.yaml"), "drive_9": "/elsewhere/drive.yaml"}
    doc["settings"] = {"references": {"drive_0": str(truth / "data/part.parquet"), "drive_9": None}}
    (scans / "_manifest.json").write_text(json.dumps(doc))
    corners = _dataset(tmp_path, "corner_map", "b" * 16, {"scans": "a" * 16})

    def write(staging: Path) -> dict:
        (staging / "t").write_bytes(b"t")
        return {"inputs": {"corner_map": {"dataset": "corner_map", "fingerprint": "b" * 64}}}

    publish_version(tmp_path / "maps/city", write, durable=False)
    plan = plan_gc(tmp_path, min_age_h=24)
    assert sorted(plan.keep) == sorted([raw, truth, scans, corners]) and plan.remove == [old_raw]


def test_gc_removes_the_scratch_of_killed_runs_and_keeps_a_live_runs(tmp_path):
    """ROOT/tmp entries a killed run left (a ledger, a task's scratch) go once nothing in them changed for
    --min-age-h; one with a recent file inside (a run in progress) stays, and so does its folder."""
    from mapservice.gc import apply_gc, plan_gc

    tmp = tmp_path / "tmp"
    ledger = tmp / "verified-0123456789ab"
    ledger.mkdir(parents=True)
    (ledger / "a.ok").write_bytes(b"z" * 300)
    scratch = tmp / "corners-drive0-chunk0001-feedbeef"
    (scratch / "sub").mkdir(parents=True)
    (scratch / "sub" / "old.bin").write_bytes(b"w" * 700)
    live = tmp / "verified-live0000000"
    live.mkdir()
    (live / "old.ok").write_bytes(b"o")
    stray = tmp / "stray.txt"
    stray.write_bytes(b"s" * 20)
    for p in (ledger / "a.ok", ledger, scratch / "sub" / "old.bin", scratch / "sub", scratch, live / "old.ok", live,
              stray):
        os.utime(p, (0, 0))
    (live / "new.ok").write_bytes(b"n")  # written now: the run is alive
    plan = plan_gc(tmp_path, min_age_h=24)
    assert plan.stale_scratch == sorted([ledger, scratch, stray]) and plan.scratch_bytes == 1020
    res = cornermap("gc", "--root", str(tmp_path))
    assert res.returncode == 0 and "3 scratch folder(s) of killed runs, 0.0 MiB" in res.stdout
    assert ledger.exists()  # a dry run deletes nothing
    apply_gc(tmp_path, plan)
    assert not ledger.exists() and not scratch.exists() and not stray.exists()
    assert (live / "old.ok").exists() and (live / "new.ok").exists()
    assert plan_gc(tmp_path, min_age_h=0).stale_scratch == [live]  # --min-age-h 0: everything


def test_rebuild_quarantines_a_bad_drive_with_its_reason_and_goes_on(tmp_path):
    create_map(tmp_path, "city", ORIGIN)
    inbox = tmp_path / "inbox"
    for name, text in (("drive_bad", "name: drive_bad\nsensor: hdl32e\nscans: {folder: nowhere, format: pcd}\n"),
                       ("bad name!", "name: x\n")):
        (inbox / name).mkdir(parents=True)
        (inbox / name / "drive.yaml").write_text(text)
    res = cornermap("rebuild", "--root", str(tmp_path), "--map", "city", "--inbox", str(inbox),
                    "--quiet-period-min", "0")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == 3 and lines[-1].startswith("nothing to do") and "quarantined drive_bad" in res.stdout
    q = inbox / "quarantine"
    assert sorted(p.name for p in q.iterdir()) == ["bad name!", "bad name!.reason.txt", "drive_bad",
                                                   "drive_bad.reason.txt"]
    assert "`cornermap drive check` refused it" in (q / "drive_bad.reason.txt").read_text()
    assert "not allowed" in (q / "bad name!.reason.txt").read_text()
    assert read_identity(tmp_path / "maps/city").drives == [] and not (tmp_path / "maps/city/LATEST").exists()
    again = cornermap("rebuild", "--root", str(tmp_path), "--map", "city", "--inbox", str(inbox))
    assert again.returncode == 0 and again.stdout.startswith("nothing to do")  # quarantine/ is not searched


def _fake_build(monkeypatch, tmp_path, cand_ekf_rms: float, prev_ekf_rms: float = 0.10):
    """rebuild's orchestration with the build and the evaluations replaced: the build publishes a held candidate
    (real publisher), the evaluations return known figures; the gate's comparison, LATEST and identity are real."""
    import mapservice.gate
    import mapservice.maps
    import mapservice.rebuild
    import pipeline.api

    drive = tmp_path / "inbox" / "drive_new" / "drive.yaml"
    drive.parent.mkdir(parents=True, exist_ok=True)
    drive.write_text("name: drive_new\n")
    published = {}

    def execute_workflow(path, **kw):
        published["v"] = _publish(tmp_path / "maps/city", b"candidate", move_latest=False).version
        return {"summary": {}, "plan": None}

    def evaluate(mdir, version, drive, reference, out):
        return _metrics(cand_ekf_rms if version == published["v"] else prev_ekf_rms)

    new = mapservice.rebuild.Selection(good=[(mapservice.rebuild.Delivery(drive.parent, drive.parent), "f" * 64, None)])
    monkeypatch.setattr(mapservice.rebuild, "select_new_drives", lambda ident, inbox, quiet_s: (new, ident))
    monkeypatch.setattr(pipeline.api, "execute_workflow", execute_workflow)
    monkeypatch.setattr(mapservice.maps, "published_version", lambda plan: published["v"])
    monkeypatch.setattr(mapservice.gate, "_evaluate", evaluate)


@pytest.mark.parametrize("cand_rms, status, latest", [(0.30, "refused", 1), (0.11, "published", 2)])
def test_rebuild_gate_moves_latest_only_when_not_worse(monkeypatch, tmp_path, cand_rms, status, latest):
    from mapservice.rebuild import RebuildParams, rebuild

    create_map(tmp_path, "city", ORIGIN)
    _publish(tmp_path / "maps/city", b"v1")
    _fake_build(monkeypatch, tmp_path, cand_rms)
    res = rebuild(tmp_path, "city", tmp_path / "inbox", RebuildParams(min_free_gib=0.0))
    mdir = tmp_path / "maps/city"
    assert res.status == status and res.exit_code == (3 if status == "refused" else 0) and res.version == 2
    assert read_latest(mdir) == latest and (mdir / "v0002/manifest.json").is_file()
    gate = json.loads((mdir / "gate/v0002.json").read_text())
    assert gate["ok"] == (status == "published") and gate["previous"] == 1
    names = [d.name for d in read_identity(mdir).drives]
    assert names == ([] if status == "refused" else ["drive_new"])
    assert any("ekf.rms_2d_m" in line for line in res.lines)

