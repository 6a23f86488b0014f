"""The exit contract of the installed ``cornermap``, run as a process (the venv's console script) the way cron, a
systemd unit or a shell runs it: exit code, one line on stderr, no traceback, nothing left running.

0 ok, 1 error, 2 usage, 3 data quality, 130 interrupted (SIGINT), 143 terminated (SIGTERM; tests/pipeline/
test_engine.py). On the LiDAR-free toy workflow (tests/pipeline/toy_stages.py) and a synthetic published map, so the
default suite stays fast; the real gate refusal of ``cornermap rebuild`` on the tiny preset is ``slow``.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from fixtures.cli import PLAIN_LINE, message_lines, one_error_line
from tests.pipeline.test_engine import write_toy
from tests.pipeline.toy_stages import EXTRA

REPO = Path(__file__).resolve().parents[1]
CORNERMAP = str(Path(sys.executable).parent / "cornermap")


def _env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("CORNERMAP_ROOT", "CORNERMAP_PROGRESS")}
    env.update(CORNERMAP_EXTRA_STAGES=EXTRA, PYTHONPATH=str(REPO), COLUMNS="120", **extra)
    return env


def cornermap(*args: str, cwd: Path, timeout: float = 180, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([CORNERMAP, *args], cwd=cwd, env=_env(**env), capture_output=True, text=True,
                          timeout=timeout)


def test_help_with_h_and_usage_errors_exit_2(tmp_path):
    for args in (("-h",), ("--help",), ("tiles", "export", "-h"), ("rebuild", "-h"), ("corners", "params", "-h")):
        res = cornermap(*args, cwd=tmp_path)
        assert res.returncode == 0 and "Usage: cornermap" in res.stdout, (args, res.stderr)
    res = cornermap(cwd=tmp_path)  # no command: the help, and the command line was not a command
    assert res.returncode == 2 and "Usage: cornermap" in res.stdout and "Traceback" not in res.stderr
    for args, says in ((("bogus",), "No such command 'bogus'"),
                       (("build", "--bogus"), "No such option: --bogus"),
                       (("build", "--drive", "d.yaml", "--map", "city"), "Missing option '--root'"),
                       (("tiles", "verify", "--root", "r", "--version", "v1"), "--map-version v1"),
                       (("evaluate", "--root", "r", "--version", "2", "--drive", "d", "--out", "o"), "--map-version 2"),
                       (("build", "--drive", "d.yaml", "--map", "city", "--root", "r", "--origin", "1,2"),
                        "--origin: expected LAT,LON,H")):
        res = cornermap(*args, cwd=tmp_path)
        line = one_error_line(res)
        assert res.returncode == 2 and line.startswith("error: ") and says in line and "--help" in line, (args, line)
    assert not (tmp_path / "r").exists()  # a usage error writes nothing


def test_run_json_is_the_only_stdout_and_progress_is_plain_lines_on_stderr(tmp_path):
    path = write_toy(tmp_path)
    dry = cornermap("run", str(path), "--dry-run", "--json", cwd=tmp_path)
    assert [(s["stage"], s["decision"]) for s in json.loads(dry.stdout)["stages"]] == [
        ("numbers", "run"), ("squares", "run"), ("total", "run")], dry.stdout
    res = cornermap("run", str(path), "--scheduler", "local", "--workers", "2", "--json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)  # stdout holds the JSON document and nothing else
    assert doc["root"] == str(tmp_path / "root") and set(doc["stages"]) == {"numbers", "squares", "total"}
    for stage in doc["stages"].values():
        assert stage["decision"] == "ran" and stage["wall_s"] >= 0 and stage["cpu_s"] >= 0
    assert doc["wall_s"] > 0 and doc["cpu_s"] > 0
    progress = [ln for ln in res.stderr.splitlines() if PLAIN_LINE.match(ln)]
    assert any(re.search(r" squares: done 8/8 in \d:\d\d:\d\d$", ln) for ln in progress), res.stderr
    assert any(" total: started" in ln for ln in progress), res.stderr

    again = cornermap("run", str(path), "-q", cwd=tmp_path)  # the closing summary: per-stage times, then totals
    assert again.returncode == 0 and again.stderr == ""
    assert re.search(r"stage\s+decision\s+partitions\s+wall s\s+CPU s", again.stdout), again.stdout
    assert re.search(r"squares\s+skipped", again.stdout) and re.search(r"total\s+[\d.]+\s+[\d.]+$", again.stdout)


def test_a_quality_refusal_exits_3_with_one_line_on_the_local_pool_and_on_a_dask_cluster(tmp_path):
    path = write_toy(tmp_path, params={"total": {"refuse": True}})
    for scheduler, root in (("local", "r_local"), ("distributed", "r_dask")):
        res = cornermap("run", str(path), "--root", root, "--scheduler", scheduler, "--workers", "2", cwd=tmp_path)
        line = one_error_line(res)
        assert res.returncode == 3 and line.startswith("error: toy total: the quality gate refused"), res.stderr
        assert not list((tmp_path / root / "datasets" / "toy_total").glob("*/_manifest.json"))
    # dask's own lines (INFO, "Compute Failed" with its traceback) go to a file under the root's tmp, not the terminal
    assert "distributed" not in res.stderr.replace("--scheduler distributed", "")
    [dashboard] = [ln for ln in res.stderr.splitlines() if "dask dashboard: " in ln]
    assert "http://127.0.0.1:" in dashboard
    [log] = list((tmp_path / "r_dask" / "tmp").glob("dask-*.log"))
    assert "Compute Failed" in log.read_text() and str(log) in dashboard


def test_tiles_and_maps_json(tmp_path):
    from tests.stages.tiles.tiles_synth import publish_two_versions

    root = publish_two_versions(tmp_path / "pub")
    ls = cornermap("tiles", "ls", "--root", str(root), "--json", cwd=tmp_path)
    doc = json.loads(ls.stdout)
    assert ls.returncode == 0 and doc["latest"] == "v0002" and [v["version"] for v in doc["versions"]] == [
        "v0001", "v0002"] and doc["versions"][1]["latest"] and doc["versions"][1]["parent_version"] == "v0001"
    verify = cornermap("tiles", "verify", "--all", "--map", "city", "--json", cwd=tmp_path, CORNERMAP_ROOT=str(root))
    doc = json.loads(verify.stdout)  # --root from the environment, as every command takes it
    assert verify.returncode == 0 and doc["ok"] and [v["ok"] for v in doc["versions"]] == [True, True]
    res = cornermap("maps", "create", "--root", "maps", "--map", "kept", "--origin", "37.4979,127.0276,57",
                    cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    show = cornermap("maps", "show", "--root", "maps", "--map", "kept", "--json", cwd=tmp_path)
    doc = json.loads(show.stdout)
    assert doc["map"] == "kept" and doc["enu_origin"]["lat_deg"] == pytest.approx(37.4979) and doc["drives"] == []


def _pool_processes(pid: int) -> list[int]:
    try:
        return [c.pid for c in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _interrupt_mid_stage(tmp_path: Path, params: dict, committed_first: str, whole_group: bool):
    """A toy run on the local pool, SIGINT once ``committed_first`` is committed (a stage sleeps 30 s then):
    to the process group as a terminal's Ctrl-C does, or to the command's process alone (``kill -INT``)."""
    path = write_toy(tmp_path, params=params)
    proc = subprocess.Popen([CORNERMAP, "run", str(path), "--scheduler", "local", "--workers", "2"], cwd=tmp_path,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    done = tmp_path / "root" / "datasets" / committed_first
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None and not list(done.glob("*/_manifest.json")):
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    time.sleep(1.5)  # the next stage's partitions are sleeping
    children = _pool_processes(proc.pid)
    t0 = time.time()
    try:
        if whole_group:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=40)
        left = [p for p in children if _alive(p)]
        deadline = time.time() + 5
        while left and time.time() < deadline:
            time.sleep(0.1)
            left = [p for p in left if _alive(p)]
    finally:  # whatever outlived it (its own session's group)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, out, err, time.time() - t0, left, path


@pytest.mark.parametrize("whole_group", [True, False], ids=["ctrl-c", "kill-int"])
def test_sigint_in_the_pool_exits_130_with_one_line_and_leaves_no_process(tmp_path, whole_group):
    code, out, err, took, left, path = _interrupt_mid_stage(tmp_path, {"squares": {"sleep_s": 30.0}}, "toy_numbers",
                                                            whole_group)
    assert code == 130, err
    assert took < 20, "SIGINT must not wait for the sleeping partitions (30 s)"
    lines = message_lines(err)
    assert lines == [lines[0]] and lines[0].startswith("interrupted: SIGINT;") and "Traceback" not in err, err
    assert not left, f"processes {left} outlived the interrupted command"
    squares = tmp_path / "root" / "datasets" / "toy_squares"
    assert not list(squares.glob("*/_manifest.json")), "an interrupted stage is not committed"
    assert not [p for p in squares.rglob("*") if p.is_file() and ".tmp" in p.name], "nothing half-written is left"
    res = cornermap("run", str(path), "-q", "--params", str(_params(tmp_path, {"squares": {"sleep_s": 0.0}})),
                    cwd=tmp_path)
    assert res.returncode == 0 and re.search(r"numbers\s+skipped", res.stdout), res.stdout + res.stderr


def test_sigint_in_a_single_partition_stage_exits_130_at_once(tmp_path):
    """The single-partition stage runs in a thread of the command's process (``pipeline.flow``): the command does
    not wait for it to finish its stage."""
    code, out, err, took, left, _ = _interrupt_mid_stage(tmp_path, {"total": {"sleep_s": 30.0}}, "toy_squares",
                                                         True)
    assert code == 130 and took < 10 and "interrupted: SIGINT;" in err and "Traceback" not in err, err
    assert not left and not list((tmp_path / "root" / "datasets" / "toy_total").glob("*/_manifest.json"))


def _params(tmp_path: Path, doc: dict) -> Path:
    import yaml

    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.slow  # a tiny build, a rebuild with a second drive and the gate's two evaluations: ~4 min
def test_a_refused_rebuild_exits_3_and_keeps_latest(tmp_path):
    sim = tmp_path / "sim"
    res = cornermap("simulate", "--preset", "tiny", "--seed", "811", "--drives", "2", "--out", str(sim), "-q",
                    cwd=tmp_path, timeout=600)
    assert res.returncode == 0, res.stderr
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for name in ("survey", "drive_0"):  # delivered: moved in whole (a drive's survey path is ../survey)
        (sim / name).rename(inbox / name)
    args = ("--root", "maps", "--map", "city")
    assert cornermap("maps", "create", *args, "--origin", "37.4979,127.0276,57", cwd=tmp_path).returncode == 0
    # delivered just now: taken at once (no quiet period to wait out; operators use it or a READY marker)
    first = cornermap("rebuild", *args, "--inbox", str(inbox), "--quiet-period-min", "0", "--json", cwd=tmp_path,
                      timeout=1200)
    assert first.returncode == 0 and json.loads(first.stdout)["status"] == "published", first.stderr
    (sim / "drive_1").rename(inbox / "drive_1")
    res = cornermap("rebuild", *args, "--inbox", str(inbox), "--quiet-period-min", "0", "--gate-tol-m", "0",
                    "--gate-tol-rel", "0", "--json", cwd=tmp_path, timeout=1800)
    doc = json.loads(res.stdout)
    if doc["status"] == "published":  # the candidate was not worse by a single figure: nothing to refuse
        pytest.skip("the second drive made no figure worse; the gate had nothing to refuse")
    assert res.returncode == 3 and doc["status"] == "refused" and doc["exit_code"] == 3, res.stderr
    assert "Traceback" not in res.stderr
    assert (tmp_path / "maps" / "maps" / "city" / "LATEST").read_text().startswith("v0001")
    assert any(" gate: " in ln for ln in res.stderr.splitlines() if PLAIN_LINE.match(ln)), res.stderr


@pytest.mark.parametrize("quiet", [True, False])
def test_an_interrupted_command_leaves_no_resource_tracker_warning(quiet):
    """A command ended by a signal while a pool's semaphores exist (``os._exit``, as ``main`` does when a stage still
    computes in a thread): the tracker process unlinks them without a warning on the user's stderr (and, the oracle,
    with one when the filter is not set)."""
    code = ("import os, multiprocessing as mp\n"
            "from mapservice.cli import quiet_resource_tracker\n"
            f"{'quiet_resource_tracker()' if quiet else 'pass'}\n"
            "lock = mp.get_context('spawn').Lock()\n"
            "os._exit(130)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=60)
    assert res.returncode == 130
    assert ("leaked semaphore" in res.stderr) is not quiet, res.stderr
