"""An operator's accidents with the maintenance loop's writers, run as processes (the installed ``cornermap``):
a build or a rollback while a rebuild holds the map, gc while a run writes, a run while gc deletes, a gate
evaluation outliving its rebuild. Nothing lost, nothing published that should not be, exit 75 with one line naming
the holder; readers never blocked. Cheap set-ups: the toy workflow (tests/pipeline/toy_stages.py) and locks held by
a helper process through the same functions the writers use (``pipeline.locks``).
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
import yaml

from fixtures.cli import one_error_line
from mapservice.maps import create_map, read_identity
from pipeline.versioned import list_versions, publish_version, read_latest
from tests.pipeline.toy_stages import EXTRA

REPO = Path(__file__).resolve().parents[1]
CM = Path(sys.executable).with_name("cornermap")
ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}
pytestmark = pytest.mark.skipif(not CM.is_file(), reason=f"no installed console script at {CM}")


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "CORNERMAP_EXTRA_STAGES": EXTRA}


def cornermap(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([str(CM), *args], capture_output=True, text=True, env=_env(), **kw)


@contextlib.contextmanager
def held(call: str):
    """A helper process that holds ``call`` (a ``pipeline.locks`` context manager) until the block ends."""
    code = ("import sys, time\nfrom pathlib import Path\nfrom pipeline.locks import *\n"
            f"with {call}:\n    print('held', flush=True)\n    time.sleep(300)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=_env())
    try:
        assert proc.stdout.readline().strip() == "held"
        yield proc
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()


def _publish(mdir: Path, payload: bytes, move_latest: bool = True) -> int:
    def write(staging: Path) -> dict:
        (staging / "tile.bin").write_bytes(payload)
        return {"enu_origin": ORIGIN, "source_drives": []}

    return publish_version(mdir, write, durable=False, move_latest=move_latest).version


def _one_line_75(res: subprocess.CompletedProcess, holder_pid: int) -> None:
    assert res.returncode == 75, (res.returncode, res.stdout, res.stderr)
    one_error_line(res)
    assert f"held by pid={holder_pid}" in res.stderr, res.stderr


def _toy(tmp: Path, sleep_s: float = 0.0, map_name: str = "city") -> Path:
    (tmp / "catalog").mkdir(exist_ok=True)
    (tmp / "catalog" / "toy.yaml").write_text(yaml.safe_dump({"datasets": {
        "toy_numbers": {"schema": "tests.pipeline.toy_stages:NUMBERS", "partitioning": ["drive", "chunk"]},
        "toy_squares": {"schema": "tests.pipeline.toy_stages:SQUARES", "partitioning": ["drive", "chunk"]},
        "toy_notes": {"kind": "artifacts"},
        "toy_total": {"schema": "tests.pipeline.toy_stages:TOTAL"}}}))
    for d in ("d0", "d1"):
        (tmp / d).mkdir(exist_ok=True)
        (tmp / d / "drive.yaml").write_text(f"name: {d}\n")
    wf = {"name": "toy", "catalog": [str(tmp / "catalog")], "scheduler": "sync", "map_name": map_name,
          "drives": [{"name": d, "path": str(tmp / d / "drive.yaml")} for d in ("d0", "d1")],
          "stages": ["numbers", "squares", "total"], "params": {"squares": {"sleep_s": sleep_s}}}
    path = tmp / "toy.yaml"
    path.write_text(yaml.safe_dump(wf))
    return path


def test_a_build_or_a_rollback_while_a_rebuild_holds_the_map_exits_75_and_publishes_nothing(tmp_path):
    root = tmp_path / "root"
    create_map(root, "city", ORIGIN)
    mdir = root / "maps" / "city"
    _publish(mdir, b"v1")
    _publish(mdir, b"v2")
    drive = tmp_path / "d0" / "drive.yaml"
    drive.parent.mkdir()
    drive.write_text("name: d0\n")
    before = (list_versions(mdir), (mdir / "LATEST").read_bytes(), read_identity(mdir))
    with held(f"writer_locks(Path({str(root)!r}), 'city', 'cornermap rebuild --map city')") as rebuild:
        res = cornermap("build", "--drive", str(drive), "--map", "city", "--root", str(root))
        _one_line_75(res, rebuild.pid)
        assert "cornermap rebuild --map city" in res.stderr
        res = cornermap("tiles", "rollback", "--to", "v0001", "--map", "city", "--root", str(root))
        _one_line_75(res, rebuild.pid)
        for reader in (("tiles", "ls"), ("maps", "show")):  # readers are never blocked
            res = cornermap(*reader, "--map", "city", "--root", str(root))
            assert res.returncode == 0, (reader, res.stderr)
    assert (list_versions(mdir), (mdir / "LATEST").read_bytes(), read_identity(mdir)) == before
    res = cornermap("tiles", "rollback", "--to", "v0001", "--map", "city", "--root", str(root))
    assert res.returncode == 0 and read_latest(mdir) == 1, res.stderr  # the holder gone: accepted


def _wait_for(predicate, proc: subprocess.Popen, seconds: float = 90.0) -> None:
    deadline = time.time() + seconds
    while time.time() < deadline and proc.poll() is None and not predicate():
        time.sleep(0.1)
    assert proc.poll() is None and predicate(), "the run should be in progress"


def test_gc_apply_while_a_run_writes_exits_75_and_the_run_keeps_its_data(tmp_path):
    root = tmp_path / "root"
    wf = _toy(tmp_path, sleep_s=1.5)
    run = subprocess.Popen([str(CM), "run", str(wf), "--root", str(root), "--quiet"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=_env())
    try:
        _wait_for(lambda: list((root / "datasets" / "toy_numbers").glob("*/_manifest.json"))
                  and list((root / "datasets" / "toy_squares").glob("*/_parts/*.json")), run)
        res = cornermap("gc", "--root", str(root), "--apply", "--min-age-h", "0")  # would take the run's folders
        _one_line_75(res, run.pid)
        assert "exclusive" in res.stderr and "cornermap run" in res.stderr
        out, err = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    assert run.returncode == 0, err
    for ds in ("toy_numbers", "toy_squares", "toy_total"):
        assert list((root / "datasets" / ds).glob("*/_manifest.json")), f"{ds} lost"
    again = subprocess.run([str(CM), "run", str(wf), "--root", str(root), "--dry-run"], capture_output=True,
                           text=True, env=_env())
    assert again.returncode == 0 and again.stdout.count("(committed)") == 3, again.stdout
    res = cornermap("gc", "--root", str(root), "--apply", "--min-age-h", "0")  # the run ended: gc runs
    assert res.returncode == 0, res.stderr


def test_a_run_while_gc_deletes_exits_75_and_writes_nothing(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    wf = _toy(tmp_path)
    with held(f"root_exclusive(Path({str(root)!r}), 'cornermap gc --apply')") as gc:
        res = cornermap("run", str(wf), "--root", str(root), "--quiet")
        _one_line_75(res, gc.pid)
        assert "cornermap gc --apply" in res.stderr
    assert not (root / "datasets").exists()
    assert cornermap("run", str(wf), "--root", str(root), "--quiet").returncode == 0


def test_two_runs_share_the_root_but_not_the_map_they_publish(tmp_path):
    """Runs of one root hold it shared (no refusal between them); a run that publishes a map holds that map."""
    root = tmp_path / "root"
    wf = _toy(tmp_path)
    with held(f"writer_locks(Path({str(root)!r}), None, 'cornermap run other.yaml')"):
        assert cornermap("run", str(wf), "--root", str(root), "--quiet").returncode == 0
    with held(f"map_lock(Path({str(root / 'maps' / 'city')!r}), 'cornermap tiles rollback')"):
        res = cornermap("run", str(wf), "--root", str(root), "--quiet")  # the toy publishes no map: not refused
        assert res.returncode == 0, res.stderr


def test_gc_min_age_h_must_be_hours_not_negative(tmp_path):
    (tmp_path / "datasets").mkdir()
    usage = cornermap("gc", "--root", str(tmp_path), "--no-such-option")
    for bad in ("-1", "nan", "-inf"):
        res = cornermap("gc", "--root", str(tmp_path), "--apply", "--min-age-h", bad)
        assert res.returncode == usage.returncode != 0, (bad, res.returncode, res.stderr)  # exit like any usage error
        assert "--min-age-h" in one_error_line(res), res.stderr
    assert (tmp_path / "datasets").is_dir()


def _children_running(pid: int) -> list[int]:
    try:
        return [c.pid for c in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def test_a_command_the_rebuild_started_ends_when_the_rebuild_is_killed(tmp_path):
    """The regression gate runs ``cornermap evaluate`` through ``mapservice.rebuild.cli``; a SIGKILLed rebuild must not
    leave it running (it outlived the rebuild by 10-20 s). Here the child is a toy run sleeping 30 s per partition."""
    wf = _toy(tmp_path, sleep_s=30.0)
    code = (f"from mapservice.rebuild import cli\ncli('run', {str(wf)!r}, '--root', {str(tmp_path / 'root')!r}, "
            "'--quiet')\n")
    parent = subprocess.Popen([sys.executable, "-c", code], env=_env(), start_new_session=True)
    try:
        deadline = time.time() + 60
        while time.time() < deadline and not list((tmp_path / "root" / "datasets" / "toy_numbers").glob(
                "*/_manifest.json")):
            time.sleep(0.1)
        time.sleep(1.0)  # in squares, sleeping
        children = _children_running(parent.pid)
        assert children, "the rebuild's child should be running"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.time() + 10
        while time.time() < deadline and any(psutil.pid_exists(c) and psutil.Process(c).status() !=
                                             psutil.STATUS_ZOMBIE for c in children):
            time.sleep(0.1)
        left = [c for c in children if psutil.pid_exists(c) and psutil.Process(c).status() != psutil.STATUS_ZOMBIE]
        assert not left, f"{left} outlived the rebuild by 10 s"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(parent.pid, signal.SIGKILL)


def test_tiles_ls_and_maps_show_mark_a_refused_candidate(monkeypatch, tmp_path):
    """A real gate refusal (the rebuild's orchestration with the build and the evaluations replaced, as in
    tests/pipeline/test_maps.py), then the listings as processes."""
    from mapservice.rebuild import RebuildParams, rebuild
    from tests.mapservice.test_maps import _fake_build

    create_map(tmp_path, "city", ORIGIN)
    _publish(tmp_path / "maps" / "city", b"v1")
    _fake_build(monkeypatch, tmp_path, cand_ekf_rms=0.30)
    res = rebuild(tmp_path, "city", tmp_path / "inbox", RebuildParams(min_free_gib=0.0))
    assert res.status == "refused" and res.version == 2
    ls = cornermap("tiles", "ls", "--map", "city", "--root", str(tmp_path))
    line = next(x for x in ls.stdout.splitlines() if "v0002" in x)
    assert ls.returncode == 0 and "REFUSED by the regression gate" in line and not line.startswith("*"), ls.stdout
    assert "REFUSED" not in next(x for x in ls.stdout.splitlines() if "v0001" in x)
    show = cornermap("maps", "show", "--map", "city", "--root", str(tmp_path))
    assert show.returncode == 0, show.stderr
    assert any(x.startswith("v0002") and "REFUSED" in x for x in show.stdout.splitlines()), show.stdout
    assert any(x.startswith("v0001") and x.endswith("LATEST") for x in show.stdout.splitlines()), show.stdout
    gate = json.loads((tmp_path / "maps" / "city" / "gate" / "v0002.json").read_text())
    assert gate["ok"] is False


def test_maps_show_works_on_a_map_made_by_build(tmp_path):
    """`cornermap build` makes maps without an identity; `maps show` used to fail on them."""
    mdir = tmp_path / "maps" / "built"

    def write(staging: Path) -> dict:
        (staging / "trajectories").mkdir()
        (staging / "trajectories" / "d0.tum").write_text("1143272000.0 0 0 0 0 0 0 1\n1143272024.9 1 0 0 0 0 0 1\n")
        return {"enu_origin": ORIGIN, "source_drives": [{"drive": "d0", "trajectory": "trajectories/d0.tum"}]}

    publish_version(mdir, write, durable=False)
    res = cornermap("maps", "show", "--map", "built", "--root", str(tmp_path))
    assert res.returncode == 0, res.stderr
    assert "no identity" in res.stdout and "37.497900000" in res.stdout and "d0" in res.stdout, res.stdout
    assert any(x.startswith("d0") and x.endswith("v0001*") for x in res.stdout.splitlines()), res.stdout
