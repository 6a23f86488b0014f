"""A real recorded drive as a mapping engineer brings it: the 22 KITTI HDL-64E scans of ../shared/data (linked,
never copied) and a GNSS CSV in KITTI's OXTS style (time, lat, lon, alt, yaw only: no std, no roll/pitch, no
wheel odometry, no per-point time). ``drive init`` drafts the drive file, ``drive check`` passes it, a build
publishes a map; with a scan file removed from the middle every other scan keeps its stamp and the gap stays.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from fixtures.kitti import kitti_drive_folder

pytestmark = pytest.mark.realdata
ORIGIN = {"lat_deg": 49.0111, "lon_deg": 8.4164, "h_m": 115.0}


def make_drive(folder: Path, kitti: Path, skip: set[int] = frozenset()) -> Path:
    """Scans as symbolic links to the shared files; an OXTS-style CSV along a plausible straight path
    (``fixtures.kitti``)."""
    return kitti_drive_folder(folder, kitti, ORIGIN, skip)


def init_check_build(folder: Path, root: Path) -> Path:
    from mapservice.build import write_build_workflow
    from mapservice.cli import execute_workflow
    from stages.ingest.drive_check import check_drive
    from stages.ingest.drive_init import draft_drive_file

    draft = draft_drive_file(folder)
    text = "\n".join(draft.lines) + "\n"
    assert draft.todo == ["the lidar's pose in the vehicle frame (x forward, y left, z up; here: identity, 1.7 m up)"]
    for expected in ("folder: velodyne_points", "format: pcd", "sensor: hdl64e", "lat: lat", "height: alt",
                     "heading: yaw", "angle_unit: rad", "heading_convention: enu_yaw_ccw_from_east", "base: unix"):
        assert expected in text, (expected, text)
    drive_yaml = folder / "drive.yaml"
    drive_yaml.write_text(text)
    check = check_drive(drive_yaml)
    assert check.problems == [], check.problems
    summary = "\n".join(check.summary)
    assert "roll/pitch absent" in summary and "rings per scan 64-64 of 64" in summary, summary
    workflow = write_build_workflow("map_rebuild", drives=[drive_yaml], map_name="kitti", root=root, origin=ORIGIN)
    execute_workflow(workflow, root=root, scheduler="sync", only=None, dry_run=False, quiet=True)
    return root


def committed(root: Path, dataset: str) -> pa.Table:
    [d] = [p for p in (root / "datasets" / dataset).iterdir() if (p / "_manifest.json").exists()]
    m = json.loads((d / "_manifest.json").read_text())
    t = pa.concat_tables([pq.read_table(d / f["path"]) for f in m["files"]])
    return t.sort_by("scan_id") if "scan_id" in t.column_names else t


@pytest.fixture(scope="module")
def kitti_builds(shared_data, tmp_path_factory):
    kitti = shared_data / "kitti_raw_0048_city"
    base = tmp_path_factory.mktemp("kitti_drive")
    full = init_check_build(make_drive(base / "full" / "k0048", kitti), base / "root_full")
    gap = init_check_build(make_drive(base / "gap" / "k0048", kitti, skip={10}), base / "root_gap")
    return full, gap


def test_real_kitti_drive_drafts_checks_and_publishes(kitti_builds):
    full, _ = kitti_builds
    manifest = json.loads((full / "maps" / "kitti" / "v0001" / "manifest.json").read_text())
    assert manifest["n_tiles"] > 0 and manifest["enu_origin"]["lat_deg"] == pytest.approx(ORIGIN["lat_deg"])
    poses = committed(full, "poses_optimized")
    assert poses.num_rows == 22 and np.isfinite(poses["x_m"].to_numpy()).all()
    gnss = committed(full, "poses_gnss")
    assert not any(gnss["roll_pitch_known"].to_pylist())  # no roll/pitch in the file: flagged, not zeros
    assert np.isfinite(gnss["std_east_m"].to_numpy()).all()  # the documented default, never NaN
    kinds = committed(full, "ingest_report")["kind"].to_pylist()
    assert "gnss_default" in kinds and "deskew" in kinds  # defaults and the missing per-point time are stated
    index = committed(full, "scan_index")
    assert index["scan_id"].to_pylist() == list(range(22))


def test_removed_scan_keeps_every_other_stamp_and_stays_a_gap(kitti_builds):
    full, gap = kitti_builds
    a, b = committed(full, "scan_index"), committed(gap, "scan_index")
    stamps_full = dict(zip(a["scan_id"].to_pylist(), a["stamp_ns"].to_pylist()))
    stamps_gap = dict(zip(b["scan_id"].to_pylist(), b["stamp_ns"].to_pylist()))
    assert sorted(stamps_full) == list(range(22)) and sorted(stamps_gap) == [i for i in range(22) if i != 10]
    assert all(stamps_gap[i] == stamps_full[i] for i in stamps_gap)
    edges = committed(gap, "odometry_edges")
    assert 10 not in edges["scan_id"].to_pylist() and 11 not in edges["scan_id"].to_pylist()  # no edge over it
    assert (gap / "maps" / "kitti" / "v0001" / "manifest.json").is_file()
    gaps = [r for r in committed(gap, "ingest_report").to_pylist() if r["kind"] == "scan_gap"]
    assert [(r["record"], r["count"]) for r in gaps] == [(9, 1)], gaps
