"""The README's section "Maps on S3-compatible object storage" runs as written (slow: a build, two rebuilds with
their gate, an export, on a ``tcp://`` cluster of two workers started apart).

Its ``bash`` block is run by ``bash`` from a folder outside the checkout holding ``runs/sim`` (the tiny simulation it
names) and ``runs/maps`` (the local root its ``tiles push`` reads), with three substitutions only: free ports for
5000 (the S3 server) and 8786 (the scheduler), so that it never meets another run's, and ``.venv/bin/`` for the
test's own interpreter's folder. Every command must succeed (``set -e``); then the bucket holds map ``kept`` with
two versions, LATEST v0002, and no local folder was named after the root.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_cli_process import _env

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def s3_block() -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Maps on S3-compatible object storage", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, re.S)
    assert len(blocks) == 1, "the S3 section has one bash block"
    return blocks[0]


def test_the_readme_s3_section_runs_as_written(tmp_path):
    from fixtures.s3server import free_port

    block = s3_block()
    for needed in ("fixtures.s3server", "dask scheduler", "dask worker", "cornermap build", "cornermap rebuild",
                   "cornermap tiles ls", "cornermap tiles verify", "cornermap tiles export", "open_map(\"s3://"):
        assert needed in block, needed
    assert block.count("dask worker") == 2 and block.count("cornermap rebuild") == 2
    s3_port, dask_port = free_port(), free_port()
    script = block.replace("5000", str(s3_port)).replace("8786", str(dask_port)).replace(".venv/bin/", f"{BIN}/")
    cwd = tmp_path / "work"
    (cwd / "runs").mkdir(parents=True)
    env = _env(PATH=f"{BIN}:{_env()['PATH']}")  # PYTHONPATH: the checkout (``-m fixtures.s3server``)
    env.pop("CORNERMAP_EXTRA_STAGES", None)
    env["CORNERMAP_SCRATCH"] = str(tmp_path / "scratch")  # the client's local copies in the test's folder
    for args in (("simulate", "--preset", "tiny", "--seed", "7", "--out", "runs/sim", "-q"),
                 ("build", "--drive", "runs/sim/drive_0/drive.yaml", "--map", "city", "--root", "runs/maps", "-q")):
        res = subprocess.run([str(BIN / "cornermap"), *args], cwd=cwd, env=env, capture_output=True, text=True,
                             timeout=1800)
        assert res.returncode == 0, res.stderr
    run = subprocess.run(["bash", "-c", "set -e; trap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n" + script],
                         cwd=cwd, env=env, capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "published map 'kept' v0001" in run.stdout and "published map 'kept' v0002" in run.stdout, run.stdout
    assert "LATEST = v0002" in run.stdout, run.stdout
    assert (cwd / "runs" / "kept-autoware" / "lanelet2_map.osm").is_file()
    assert not list(cwd.glob("**/s3:*")), "a local folder named after the root"
