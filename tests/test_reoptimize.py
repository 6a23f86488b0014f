"""``cornermap maps reoptimize`` as a process on the tiny city (slow: two rebuilds and two re-optimizations).

drive_0 -> v0001 (solved alone), drive_1 -> v0002 (incremental: drive_0 held; the drift statistic written and shown
by ``maps show``); ``maps reoptimize --region-max-poses 150`` -> v0003 (every drive re-solved in regions of at most
150 poses); ``maps reoptimize --region-max-poses 0`` -> v0004 (one joint graph: ``rebuild --full``'s solve).
Oracles: exit codes (0 published, 75 locked, 1 unknown map), two runs SIGKILLed at random points leave LATEST a
complete verified version and the next run completes, a new complete version each time, the old drive's
poses moved by the region solve, and the region solve equal to the joint solve within millimetres.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mapservice.maps import create_map
from tests.test_rebuild import _latest_is_verified
from tests.test_rebuild_incremental import ORIGIN, _drive, _poses, _report

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapservice", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def _xy(table, name):
    d = _drive(table, name)
    return np.column_stack([d["x_m"].to_numpy(), d["y_m"].to_numpy()])


def test_reoptimize_publishes_the_joint_solution_region_by_region(tmp_path):
    sim = tmp_path / "sim"
    assert _run("simulate", "--preset", "tiny", "--seed", "7", "--drives", "2", "--out", str(sim)).returncode == 0
    root, inbox = tmp_path / "root", tmp_path / "inbox"
    inbox.mkdir()
    shutil.copytree(sim / "survey", inbox / "survey")
    create_map(root, "city", ORIGIN)
    for k in (0, 1):
        shutil.copytree(sim / f"drive_{k}", inbox / f"drive_{k}")
        res = _run("rebuild", "--root", str(root), "--map", "city", "--inbox", str(inbox), "--min-free-gib", "0.5",
                   "--quiet-period-min", "0", "--no-gate")
        assert res.returncode == 0, res.stdout + res.stderr
    mdir = root / "maps" / "city"
    v2 = mdir / "v0002"
    drift = _report(root, v2)["incremental"]["drift"]
    assert drift["regions"] and all(r["dof"] == 6 * r["loops"] for r in drift["regions"])
    show = _run("maps", "show", "--root", str(root), "--map", "city")
    assert show.returncode == 0 and ("reoptimize advised" in show.stdout or "drift: " in show.stdout), show.stdout

    # another writer holds the map: 75, nothing written
    from mapservice.maps import run_lock

    with run_lock(mdir):
        locked = _run("maps", "reoptimize", "--root", str(root), "--map", "city", "--no-gate", "--min-free-gib", "0")
    assert locked.returncode == 75, locked.stdout + locked.stderr
    assert not (mdir / "v0003").exists()
    unknown = _run("maps", "reoptimize", "--root", str(root), "--map", "nosuch", "--no-gate")
    assert unknown.returncode == 1 and "Traceback" not in unknown.stderr

    # killed anywhere: LATEST stays a complete verified version; the next run completes from what was committed
    args = ("maps", "reoptimize", "--root", str(root), "--map", "city", "--region-max-poses", "150", "--no-gate",
            "--min-free-gib", "0")
    rng = random.Random(59)
    for _ in range(2):
        p = subprocess.Popen([sys.executable, "-m", "mapservice", *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(REPO)},
                             start_new_session=True)
        time.sleep(rng.uniform(5.0, 40.0))
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        assert _latest_is_verified(mdir) in (2, 3)
    res = _run(*args)
    assert res.returncode == 0 and "v0003" in res.stdout, res.stdout + res.stderr
    assert _latest_is_verified(mdir) == 3
    res = _run("maps", "reoptimize", "--root", str(root), "--map", "city", "--region-max-poses", "0", "--no-gate",
               "--min-free-gib", "0")
    assert res.returncode == 0 and "v0004" in res.stdout, res.stdout + res.stderr

    p2, p3, p4 = (_poses(root, mdir / f"v000{k}") for k in (2, 3, 4))
    rep3 = _report(root, mdir / "v0003")
    assert rep3.get("incremental") is None  # one graph of every drive, not an increment
    moved = np.linalg.norm(_xy(p3, "drive_0") - _xy(p2, "drive_0"), axis=1)
    assert moved.max() > 1e-4  # the old drive's poses were re-solved
    for name in ("drive_0", "drive_1"):  # the region solve is the joint solve
        diff = np.linalg.norm(_xy(p3, name) - _xy(p4, name), axis=1)
        assert np.sqrt(np.mean(diff ** 2)) < 0.003 and diff.max() < 0.01, (name, diff.max())
    truth = np.loadtxt(sim / "truth" / "drive_0_poses_tum.txt", usecols=(0, 1, 2))
    d = _drive(p3, "drive_0")
    t = d["stamp_ns"].to_numpy() * 1e-9
    err = _xy(p3, "drive_0") - np.column_stack([np.interp(t, truth[:, 0], truth[:, 1]),
                                                 np.interp(t, truth[:, 0], truth[:, 2])])
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.10
    manifest = json.loads((mdir / "v0003" / "manifest.json").read_text())
    assert len(manifest["source_drives"]) == 2
