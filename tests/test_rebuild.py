"""``cornermap rebuild`` on the tiny city, end to end (slow: several tiny builds).

One story, in order: a 3-drive inbox with one bad drive (GNSS file replaced by garbage) -> the bad one is
quarantined, the two good ones built into v0001; two rebuilds started together -> one publishes, the other
exits 75 and writes nothing; a re-run -> "nothing to do"; a third drive arrives and rebuilds are SIGKILLed
after random delays -> LATEST always names a complete, verified version; the next rebuild completes and
reused the old drives' per-drive work (linked part markers, "reused" counts).
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

import pytest

from mapformat.verify import verify_map
from mapservice.maps import create_map, read_identity
from pipeline.versioned import read_latest, trusted_manifest_digests, version_name

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]
ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "mapservice", *args]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def _latest_is_verified(mdir: Path) -> int | None:
    latest = read_latest(mdir) if (mdir / "LATEST").exists() else None
    if latest is not None:
        trusted = trusted_manifest_digests(mdir)
        assert verify_map(mdir / version_name(latest), trusted.get(latest)) == []
    return latest


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "sim"
    subprocess.run(_cmd("simulate", "--preset", "tiny", "--seed", "7", "--drives", "3", "--out", str(out)),
                   check=True, capture_output=True, env=_env())
    return out


def test_rebuild_story(sim, tmp_path):
    root, inbox = tmp_path / "root", tmp_path / "inbox"
    inbox.mkdir()
    shutil.copytree(sim / "survey", inbox / "survey")
    for name in ("drive_0", "drive_1"):
        shutil.copytree(sim / name, inbox / name)
    shutil.copytree(sim / "drive_2", inbox / "drive_bad")
    gnss = inbox / "drive_bad" / "gnss_inspva.csv"
    gnss.write_text(gnss.read_text().splitlines()[0] + "\nnot,a,gnss,row\n")
    create_map(root, "city", ORIGIN)
    mdir = root / "maps" / "city"
    args = ("rebuild", "--root", str(root), "--map", "city", "--inbox", str(inbox), "--min-free-gib", "0.5",
            "--quiet-period-min", "0")  # the drives were copied just now: take them at once

    # Two rebuilds started together: one runs, the other exits 75 having written nothing.
    procs = [subprocess.Popen(_cmd(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
             for _ in range(2)]
    outs = [p.communicate() + (p.returncode,) for p in procs]
    codes = sorted(o[2] for o in outs)
    assert codes == [0, 75], outs
    loser = next(o for o in outs if o[2] == 75)
    assert loser[0] == "" and "held by pid=" in loser[1] and len(loser[1].strip().splitlines()) == 1
    winner = next(o for o in outs if o[2] == 0)
    assert "quarantined drive_bad" in winner[0] and "published map 'city' v0001" in winner[0], winner

    assert (inbox / "quarantine" / "drive_bad").is_dir() and not (inbox / "drive_bad").exists()
    assert "gnss" in (inbox / "quarantine" / "drive_bad.reason.txt").read_text()
    assert _latest_is_verified(mdir) == 1
    assert [d.name for d in read_identity(mdir).drives] == ["drive_0", "drive_1"]
    show = subprocess.run(_cmd("maps", "show", "--root", str(root), "--map", "city"), capture_output=True,
                          text=True, env=_env())
    assert show.returncode == 0 and "v0001*" in show.stdout and "drive_1" in show.stdout, show.stdout

    # Nothing new: one line, exit 0, nothing written (but the lock files under ROOT/locks/).
    def snapshot():
        return sorted((str(p), p.stat().st_mtime_ns) for p in root.rglob("*")
                      if "locks" not in p.relative_to(root).parts)

    before = snapshot()
    res = subprocess.run(_cmd(*args), capture_output=True, text=True, env=_env())
    assert res.returncode == 0 and res.stdout.startswith("nothing to do") and len(res.stdout.splitlines()) == 1
    assert snapshot() == before

    # A third drive; rebuilds killed at random points never leave LATEST on an incomplete version.
    shutil.copytree(sim / "drive_2", inbox / "drive_2")
    rng = random.Random(23)
    for _ in range(3):
        p = subprocess.Popen(_cmd(*args), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env(),
                             start_new_session=True)
        time.sleep(rng.uniform(5.0, 60.0))
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        assert _latest_is_verified(mdir) in (1, 2)
    res = subprocess.run(_cmd(*args), capture_output=True, text=True, env=_env())
    assert res.returncode == 0, res.stdout + res.stderr
    latest = _latest_is_verified(mdir)
    # a killed run may have got to the end before its kill (a fast machine): the next one then has nothing to do
    done = f"published map 'city' {version_name(latest)}" in res.stdout or res.stdout.startswith("nothing to do")
    assert latest >= 2 and done, res.stdout
    assert [d.name for d in read_identity(mdir).drives] == ["drive_0", "drive_1", "drive_2"]
    gate = json.loads((mdir / "gate" / f"{version_name(latest)}.json").read_text())
    assert gate["ok"] and gate["previous"] == 1

    # The old drives' per-drive work was linked, not recomputed, in the 3-drive datasets.
    manifest = json.loads((mdir / version_name(latest) / "manifest.json").read_text())
    assert sorted(d["drive"] for d in manifest["source_drives"]) == ["drive_0", "drive_1", "drive_2"]
    for ds in ("scans_raw", "odometry_edges", "corners_per_scan"):
        dirs = [d for d in (root / "datasets" / ds).iterdir() if (d / "_parts").is_dir()]
        newest = max(dirs, key=lambda d: len(list((d / "_parts").glob("drive2*"))))
        markers = {m.name: json.loads(m.read_text()) for m in (newest / "_parts").glob("*.json")}
        assert all(v.get("linked_from") for k, v in markers.items() if not k.startswith("drive2")), ds
        assert not any(v.get("linked_from") for k, v in markers.items() if k.startswith("drive2")), ds
