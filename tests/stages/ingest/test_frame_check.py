"""A drive that nothing places in the map's frame: drive check accepts the drive file and says in one line what it
lacks; a build refuses it in one line before any stage runs (exit 3, nothing committed), saying what to add; a drive
that starts at the map's origin needs --origin (exit 2 without). Run as a user would: the installed command, from a
folder outside the checkout."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import yaml

from fixtures.ingest import write_synthetic_drive
from stages.ingest.drive_file import load_drive_file
from stages.ingest.frame import frame_source

CORNERMAP = [sys.executable, "-m", "mapservice"]


def _without_gnss(tmp_path, **extra) -> Path:
    drive = write_synthetic_drive(tmp_path, n_scans=3).drive_file
    doc = yaml.safe_load(drive.read_text())
    del doc["gnss"]
    doc["scan_times"] = {"source": "stamps_csv"}
    doc.update(extra)
    drive.write_text(yaml.safe_dump(doc))
    return drive


def test_what_places_a_drive(tmp_path):
    drive = _without_gnss(tmp_path / "a")
    assert frame_source(load_drive_file(drive)).kind is None
    start = {"heading_deg": 30.0, "heading_convention": "azimuth_cw_from_north"}
    drive = _without_gnss(tmp_path / "b", start=start)
    src = frame_source(load_drive_file(drive))
    assert src.kind == "start" and src.problem is None and src.needs_origin
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "p.txt").write_text("0 0 0 0 0 0 0 1\n")
    drive = _without_gnss(tmp_path / "c", prior={"file": "../p.txt", "format": "tum", "frame": "local"})
    assert "add start:" in frame_source(load_drive_file(drive)).problem
    drive = _without_gnss(tmp_path / "c", prior={"file": "../p.txt", "format": "tum", "frame": "local"}, start=start)
    assert frame_source(load_drive_file(drive)).problem is None


def test_check_accepts_and_build_refuses_in_one_line_before_any_stage_work(tmp_path):
    drive = _without_gnss(tmp_path / "drives")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    check = subprocess.run(CORNERMAP + ["drive", "check", str(drive)], cwd=outside, capture_output=True, text=True,
                           timeout=300)
    assert check.returncode == 0, check.stderr
    warning = [ln for ln in check.stdout.splitlines() if "frame cannot be fixed" in ln]
    assert len(warning) == 1 and "no GNSS, no prior trajectory, no start heading" in warning[0]
    assert "frame: none (no GNSS, no prior trajectory, no start heading)" in check.stdout
    root = tmp_path / "root"
    build = subprocess.run(CORNERMAP + ["build", "--drive", str(drive), "--map", "m", "--root", str(root),
                                        "--origin", "37.5665,126.978,38", "--quiet"],
                           cwd=outside, capture_output=True, text=True, timeout=600)
    assert build.returncode == 3, (build.stdout, build.stderr)
    lines = [ln for ln in build.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "its frame cannot be fixed" in lines[0], lines
    assert "add one of: a gnss section" in lines[0] and "Traceback" not in build.stderr
    committed = [p for p in (root / "datasets").rglob("_manifest.json")] if (root / "datasets").exists() else []
    assert committed == [], [str(p) for p in committed]
    assert not any(json.loads(p.read_text()).get("rows") for p in committed)


def test_a_drive_starting_at_the_origin_needs_one(tmp_path):
    start = {"heading_deg": 30.0, "heading_convention": "azimuth_cw_from_north"}
    drive = _without_gnss(tmp_path / "drives", start=start)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    root = tmp_path / "root"
    build = subprocess.run(CORNERMAP + ["build", "--drive", str(drive), "--map", "m", "--root", str(root),
                                        "--quiet"], cwd=outside, capture_output=True, text=True, timeout=600)
    assert build.returncode == 2, (build.stdout, build.stderr)
    lines = [ln for ln in build.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "starts at the map's origin" in lines[0] and "--origin" in lines[0], lines
    assert not (root / "datasets").exists() or not list((root / "datasets").rglob("_manifest.json"))


def test_a_keyframe_drive_with_a_start_heading_alone_is_not_placed(tmp_path):
    start = {"heading_deg": 30.0, "heading_convention": "azimuth_cw_from_north"}
    drive = _without_gnss(tmp_path / "k", start=start)
    stamps = drive.parent / "scans" / "stamps.csv"
    lines = stamps.read_text().splitlines()
    head, rows = lines[0], [ln.split(",") for ln in lines[1:]]
    col = head.split(",").index("gps_seconds")
    for k, r in enumerate(rows):  # keyframes 1.5 s apart
        r[col] = f"{float(rows[0][col]) + 1.5 * k:.6f}"
    stamps.write_text("\n".join([head] + [",".join(r) for r in rows]) + "\n")
    src = frame_source(load_drive_file(drive))
    assert src.kind == "start" and "a keyframe drive (median 1.50 s between scans)" in src.problem
    assert "add prior:" in src.problem
