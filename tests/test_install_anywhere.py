"""cornermap as a user gets it: a wheel built from the tracked files, installed into a fresh virtual environment
outside the repository, run from a folder that is not the checkout (simulate -> build --origin -> tiles verify),
then the committed root moved elsewhere and rebuilt (every stage skipped), and a replaced survey file (ingest
re-runs).

The fresh environment sees the project environment's third-party packages through a ``.pth`` line (installing
open3d and gtsam again would only test PyPI), but cornermap itself only from the wheel: the test asserts that.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ORIGIN = "37.4979,127.0276,57.0"


def _run(cmd: list[str], cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "CORNERMAP_EXTRA_STAGES")}
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, (
        f"{' '.join(map(str, cmd))} -> {out.returncode}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    )
    return out


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with cornermap installed from a wheel; returns its bin folder."""
    work = tmp_path_factory.mktemp("wheel")
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    src = work / "src"
    for rel in filter(None, files):
        path = REPO / rel.decode()
        if path.is_file():
            (src / rel.decode()).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, src / rel.decode())
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(work / "dist"),
          str(src)], cwd=work)
    [wheel] = list((work / "dist").glob("cornermap-*.whl"))
    venv = work / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], cwd=work)
    site = next((venv / "lib").glob("python3*/site-packages"))
    deps = [p for p in sys.path if p.endswith("site-packages") and Path(p).is_dir()]
    (site / "zz_project_dependencies.pth").write_text("\n".join(deps) + "\n")
    _run([str(venv / "bin" / "python"), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)], cwd=work)
    return venv / "bin"


def test_wheel_runs_from_any_folder(installed, tmp_path):
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    where = _run([str(installed / "python"), "-c", "import pipeline, workflows, data_catalog; "
                  "print(pipeline.__file__)"], cwd=cwd).stdout.strip()
    assert str(installed.parent) in where and str(REPO) not in where, where
    cm = str(installed / "cornermap")
    _run([cm, "catalog", "ls"], cwd=cwd)
    _run([cm, "simulate", "--preset", "tiny", "--seed", "5", "--out", "sim"], cwd=cwd)
    _run([cm, "drive", "check", "sim/drive_0/drive.yaml"], cwd=cwd)
    build = [cm, "build", "--drive", "sim/drive_0/drive.yaml", "--map", "city", "--root", "maps", "--origin", ORIGIN,
             "-q"]
    _run(build, cwd=cwd)
    _run([cm, "tiles", "verify", "--map", "city", "--root", "maps"], cwd=cwd)
    manifest = json.loads((cwd / "maps" / "maps" / "city" / "v0001" / "manifest.json").read_text())
    assert manifest["n_corners"] > 0
    assert manifest["enu_origin"]["lat_deg"] == pytest.approx(37.4979)

    # The committed root moved to another folder: no stage computes anything (no new fingerprint directory),
    # no version is published, and the outcome line names the new place.
    before = sorted(p.relative_to(cwd / "maps") for p in (cwd / "maps" / "datasets").glob("*/*"))
    shutil.move(str(cwd / "maps"), str(cwd / "moved"))
    again = _run(build[:-4] + ["moved", "--origin", ORIGIN], cwd=cwd).stdout
    after = sorted(p.relative_to(cwd / "moved") for p in (cwd / "moved" / "datasets").glob("*/*"))
    assert after == before
    assert not (cwd / "moved" / "maps" / "city" / "v0002").exists()
    assert "unchanged (committed by an earlier run)" in again and str(cwd / "moved") in again, again

    # A replaced survey file (same path, same size) is noticed: ingest would run again.
    survey = cwd / "sim" / "survey" / "survey.las"
    data = bytearray(survey.read_bytes())
    data[-1] ^= 0x01  # one bit of the last point record
    survey.write_bytes(bytes(data))
    workflow = next((cwd / "moved" / "workflows").glob("build-city-*.yaml"))
    dry = subprocess.run([cm, "run", str(workflow), "--root", "moved", "--dry-run"], cwd=cwd, capture_output=True,
                         text=True, env={**os.environ, "COLUMNS": "250"}, timeout=300).stdout
    ingest_row = next(line for line in dry.splitlines() if "│ ingest " in line)
    assert "run" in ingest_row and "skip" not in ingest_row, dry
