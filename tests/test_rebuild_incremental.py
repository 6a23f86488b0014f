"""``cornermap rebuild``'s incremental pose graph on the tiny city, end to end (slow: three tiny rebuilds).

drive_0 makes v0001 (a first version: solved alone); drive_1 added by a default rebuild -> v0002, solved against
v0001's poses held; drive_2 added with ``--full`` -> v0003, every drive solved jointly again. Oracles: the held
drive's poses_optimized rows and published trajectory are v0001's bit for bit, or moved rigidly by the window's
frame correction (stages/posegraph/window.py) by no more than its stated frame covariance allows; the new drive lies
on its truth; corner ids carried; the joint re-solve does move the old poses (the incremental one is not a
no-op by accident).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.dataset as pads
import pytest

from mapservice.maps import create_map
from schemas.registry import schema_of

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]
ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapservice", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def _poses(root: Path, vdir: Path):
    """The poses_optimized table the version was published from (its manifest's ``poses`` input)."""
    from pipeline.store import dataset_dir, read_manifest

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    ddir = dataset_dir(root, "poses_optimized", fp)
    files = [str(ddir / f["path"]) for f in read_manifest(ddir)["files"]]
    table = pads.dataset(files, schema=schema_of("poses_optimized"), format="parquet").to_table()
    return table.sort_by([("drive", "ascending"), ("scan_id", "ascending")])


def _drive(table, name: str):
    import pyarrow.compute as pc

    return table.filter(pc.equal(table["drive"], name))


def _report(root: Path, vdir: Path) -> dict:
    from pipeline.store import dataset_dir

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    return json.loads(next(dataset_dir(root, "posegraph_report", fp).rglob("posegraph_report.json")).read_text())


def test_incremental_rebuild_holds_the_map_and_full_resolves_it(tmp_path):
    sim = tmp_path / "sim"
    assert _run("simulate", "--preset", "tiny", "--seed", "7", "--drives", "3", "--out", str(sim)).returncode == 0
    root, inbox = tmp_path / "root", tmp_path / "inbox"
    inbox.mkdir()
    shutil.copytree(sim / "survey", inbox / "survey")
    create_map(root, "city", ORIGIN)
    args = ("rebuild", "--root", str(root), "--map", "city", "--inbox", str(inbox), "--min-free-gib", "0.5",
            "--quiet-period-min", "0", "--no-gate")
    for k, extra in ((0, ()), (1, ()), (2, ("--full",))):
        shutil.copytree(sim / f"drive_{k}", inbox / f"drive_{k}")
        res = _run(*args, *extra)
        assert res.returncode == 0 and f"published map 'city' v000{k + 1}" in res.stdout, res.stdout + res.stderr
    check_versions(root, sim)


def check_versions(root: Path, sim: Path) -> None:
    v1, v2, v3 = (root / "maps" / "city" / f"v000{k}" for k in (1, 2, 3))

    # v0002: drive_0 held (bit for bit, or moved rigidly by the window's frame correction), drive_1 solved against it
    p1, p2, p3 = _poses(root, v1), _poses(root, v2), _poses(root, v3)
    rep2 = _report(root, v2)
    if "drive_0" in rep2["incremental"]["moved_drives"]:
        a1, a2 = _drive(p1, "drive_0"), _drive(p2, "drive_0")
        x1 = np.column_stack([a1[c].to_numpy() for c in ("x_m", "y_m", "z_m")])
        x2 = np.column_stack([a2[c].to_numpy() for c in ("x_m", "y_m", "z_m")])
        assert a2["scan_id"].equals(a1["scan_id"]) and a2["cov_xy_yaw"].equals(a1["cov_xy_yaw"])
        # rigid: distances to the first pose kept (tiny's loop lies within reach of drive_1 end to end: no ramp)
        d1, d2 = (np.linalg.norm(x - x[0], axis=1) for x in (x1, x2))
        assert np.max(np.abs(d2 - d1)) < 1e-6
        frame = rep2["incremental"]["drift"]["frame"]
        assert np.linalg.norm(x2 - x1, axis=1).max() <= 5 * max(frame["prior_std_en_m"]) + 0.01
    else:
        assert _drive(p2, "drive_0").equals(_drive(p1, "drive_0"))
        assert (v2 / "trajectories" / "drive_0.tum").read_bytes() == \
            (v1 / "trajectories" / "drive_0.tum").read_bytes()
    assert rep2["incremental"]["held_version"] == 1 and rep2["incremental"]["new_drives"] == ["drive_1"]
    assert rep2["map"]["loops_accepted"] > 0
    truth = np.loadtxt(sim / "truth" / "drive_1_poses_tum.txt", usecols=(0, 1, 2))
    d1 = _drive(p2, "drive_1")
    t = d1["stamp_ns"].to_numpy() * 1e-9
    err = np.column_stack([d1["x_m"].to_numpy() - np.interp(t, truth[:, 0], truth[:, 1]),
                           d1["y_m"].to_numpy() - np.interp(t, truth[:, 0], truth[:, 2])])
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.10  # its GNSS alone: ~0.5 m RMS (simulation.json)

    # corner ids: every v0001 corner still within 5 cm in v0002 keeps its id
    from mapformat.loader import open_map

    c1, c2 = open_map(v1).all_corners(), open_map(v2).all_corners()
    from scipy.spatial import cKDTree

    en1 = np.column_stack([c1["east_m"].to_numpy(), c1["north_m"].to_numpy()])
    en2 = np.column_stack([c2["east_m"].to_numpy(), c2["north_m"].to_numpy()])
    d, k = cKDTree(en2).query(en1, distance_upper_bound=0.05)
    near = d < 0.05
    assert near.sum() >= 0.8 * len(en1)
    assert np.array_equal(c2["corner_id"].to_numpy()[k[near]], c1["corner_id"].to_numpy()[near])

    # v0003 (--full): one joint graph again, the old drives' poses move with the new loops
    assert _report(root, v3).get("incremental") is None
    a, b = _drive(p3, "drive_0"), _drive(p2, "drive_0")
    assert not np.array_equal(a["x_m"].to_numpy(), b["x_m"].to_numpy())
