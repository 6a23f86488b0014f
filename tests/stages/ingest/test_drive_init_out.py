"""``cornermap drive init FOLDER --out FILE``: the draft's paths resolve from where it is written (the README's
``drive init runs/sim/drive_0 --out runs/draft.yaml`` then ``drive check runs/draft.yaml``), run as a process."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

from fixtures.ingest import write_synthetic_drive


def _cornermap(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("cornermap")
    return subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "200"})


def test_a_draft_written_elsewhere_names_the_drive_files_from_its_own_folder(tmp_path):
    write_synthetic_drive(tmp_path / "runs" / "sim", "drive_0")
    init = _cornermap("drive", "init", "runs/sim/drive_0", "--out", "runs/draft.yaml", cwd=tmp_path)
    assert init.returncode == 0, init.stderr
    doc = yaml.safe_load((tmp_path / "runs" / "draft.yaml").read_text())
    assert doc["scans"]["folder"] == "sim/drive_0/scans"
    assert doc["gnss"]["file"].startswith("sim/drive_0/")
    check = _cornermap("drive", "check", "runs/draft.yaml", cwd=tmp_path)  # the draft's own `next:` hint
    assert check.returncode == 0, check.stdout + check.stderr
    assert "ok: runs/draft.yaml" in check.stdout
    # in a sub-folder of the drive: the paths go up to it
    init = _cornermap("drive", "init", "runs/sim/drive_0", "--out", "runs/sim/drive_0/drafts/d.yaml", cwd=tmp_path)
    assert init.returncode == 0, init.stderr
    assert yaml.safe_load((tmp_path / "runs/sim/drive_0/drafts/d.yaml").read_text())["scans"]["folder"] == "../scans"


def test_a_draft_whose_paths_would_leave_its_parent_folder_is_refused_in_one_line(tmp_path):
    write_synthetic_drive(tmp_path / "data", "drive_0")
    (tmp_path / "elsewhere" / "deep").mkdir(parents=True)
    out = _cornermap("drive", "init", "data/drive_0", "--out", "elsewhere/deep/draft.yaml", cwd=tmp_path)
    assert out.returncode == 1 and not (tmp_path / "elsewhere" / "deep" / "draft.yaml").exists()
    assert "outside the drive file's parent folder" in out.stderr and "Traceback" not in out.stderr
