"""Changelog at publish (mapformat/changelog.py via the tiles stage), `tiles log`, and `tiles diff` across frames."""
from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest
from typer.testing import CliRunner

from mapformat.changelog import CHANGELOG_FILE, read_changelog
from mapformat.loader import open_map
from pipeline.versioned import read_manifest
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import ORIGIN, building_corners, buildings, city_context, corner_table

DEMOLISHED = 14  # block (2, 2): tile (1, 1)
MOVED_ROW = 0  # this corner of v1 is rebuilt 0.5 m further east in v2


def _ids_by_position(reader, xy: np.ndarray) -> np.ndarray:
    t = reader.all_corners()
    en = np.column_stack([t["east_m"].to_numpy(), t["north_m"].to_numpy()])
    d = np.linalg.norm(en[None, :, :] - xy[:, None, :], axis=2)
    return t["corner_id"].to_numpy()[d.argmin(axis=1)]


@pytest.fixture(scope="module")
def history(tmp_path_factory):
    """v1: the city; v2: one building demolished, one corner moved 0.5 m, one building built at (400, 50) m,
    corners renumbered and listed in another order by the corner stage."""
    root = tmp_path_factory.mktemp("log")
    xy, dirs, owner = building_corners(buildings())
    v1 = corner_table(xy, dirs, seed=1)  # each corner merged from 60 scans: seen by most scans in view of it
    v1 = v1.set_column(v1.schema.get_field_index("n_obs"), "n_obs", pa.array(np.full(len(xy), 60, np.int64)))
    compute(city_context(root, v1))
    new_xy, new_dirs, _ = building_corners(np.array([[400.0, 40.0, 430.0, 60.0]]))
    keep = owner != DEMOLISHED
    xy2 = xy.copy()
    xy2[MOVED_ROW] += [0.5, 0.0]
    both_xy, both_dirs = np.vstack([new_xy, xy2[keep]]), np.vstack([new_dirs, dirs[keep]])
    perm = np.random.default_rng(0).permutation(len(both_xy))
    compute(city_context(root, corner_table(both_xy[perm], both_dirs[perm], seed=2, first_id=1), fingerprint="fp2"))
    d = root / "maps" / "city"
    return root, d, xy, owner, new_xy


def test_changelog_lists_removed_added_moved_corners_with_stable_ids(history):
    _, d, xy, owner, new_xy = history
    v1, v2 = open_map(d, 1), open_map(d, 2)
    log = read_changelog(v2.path, v2.manifest)
    assert CHANGELOG_FILE in v2.manifest["files"] and v2.manifest["changelog"] == CHANGELOG_FILE
    ids1 = _ids_by_position(v1, xy)
    keep = owner != DEMOLISHED
    ids2 = _ids_by_position(v2, np.where((np.arange(len(xy)) == MOVED_ROW)[:, None], xy + [0.5, 0], xy)[keep])
    assert (ids2 == ids1[keep]).all()  # every surviving corner, the moved one too, keeps its id
    c = log["corners"]
    # the drive (east = 50, 150, 250 m) sees the demolished building's east face only: its two west corners are
    # beyond 60 m of it, so v2 cannot say they are gone (not re-observed); the east ones, in view of tens of scans
    # of v2's drive, are removed; the new building at (400, 50) m is 150 m
    # from any drive: v1 never looked there (newly observed, not added)
    gone = c["removed"] + c["not_reobserved"]
    assert sorted(e["id"] for e in gone) == sorted(ids1[~keep].tolist())
    assert sorted(e["east_m"] for e in c["removed"]) == pytest.approx([140.0, 140.0], abs=0.05)
    assert all(e["tile"] == [1, 1] for e in gone)
    assert c["added"] == []
    added = sorted(e["id"] for e in c["newly_observed"])
    assert added == sorted(_ids_by_position(v2, new_xy).tolist())
    assert min(added) > ids1.max() and c["next_corner_id"] == max(added) + 1 == v2.manifest["next_corner_id"]
    assert [(e["id"], e["dist_m"]) for e in c["moved"]] == [(int(ids1[MOVED_ROW]), pytest.approx(0.5, abs=0.03))]
    # moved by the chi-square test on both covariances (0.05 m-class: 0.5 m is far beyond), the rest unchanged
    assert c["moved"][0]["chi2"] > c["test"]["threshold"] == pytest.approx(13.816, abs=1e-3) and c["test"]["dof"] == 2
    assert c["unchanged"] == c["kept"] - 1
    assert (c["n_before"], c["n_after"], c["kept"]) == (len(xy), keep.sum() + 4, keep.sum())
    assert log["parent_version"] == 1 and log["frame"]["unchanged"] is True
    assert log["frame"]["enu_origin"]["lat_deg"] == ORIGIN.lat_deg
    m = log["markings"]  # same rasters both times
    assert (m["tiles"], m["total_px_changed"], m["cells"], m["test"]["cells_compared"] > 0) == ([], 0, [], True)
    first = read_changelog(v1.path, v1.manifest)
    assert first["parent_version"] is None and first["frame"]["unchanged"] is None
    assert len(first["corners"]["added"]) == len(xy) and first["drives"]["added"] == ["drive_a"]


def test_changelog_is_checksummed(history):
    _, d, *_ = history
    v2 = open_map(d, 2)
    path = v2.path / CHANGELOG_FILE
    original = path.read_bytes()
    try:
        path.write_bytes(original.replace(b'"kept"', b'"kepT"'))
        from pipeline.errors import IntegrityError

        with pytest.raises(IntegrityError):
            read_changelog(v2.path, read_manifest(v2.path)[0])
    finally:
        path.write_bytes(original)


def _app():
    import typer

    from stages.tiles.cli import register

    app = typer.Typer()
    register(app)
    return app


def test_tiles_log_prints_the_history(history):
    app = _app()
    root, _, xy, _, _ = history
    res = CliRunner().invoke(app, ["tiles", "log", "--root", str(root), "--map", "city", "--details"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    v1 = next(s for s in lines if "v0001" in s and "parent=" in s)
    v2 = next(s for s in lines if "v0002" in s and "parent=" in s)
    assert f"+{len(xy)} -0 ~0" in v1 and "first version" in v1
    assert "parent=v0001" in v2 and "+0 -2 ~1 (+4 newly observed, -2 not re-observed)" in v2 \
        and "frame unchanged" in v2 and v2.startswith("*")
    assert any(s.strip().startswith("removed: #") for s in lines)
    res = CliRunner().invoke(app, ["tiles", "log", "--root", str(root), "--map", "city", "--json"])
    docs = json.loads(res.output)
    assert [x["version"] for x in docs] == ["v0001", "v0002"] and docs[1]["changelog"]["parent_version"] == 1


def test_marking_pixels_changed_per_tile(tmp_path):
    import cv2

    xy, dirs, _ = building_corners(buildings())
    compute(city_context(tmp_path, corner_table(xy, dirs, seed=1)))
    ctx = city_context(tmp_path, corner_table(xy, dirs, seed=1), fingerprint="fp2")
    mask_file = next((tmp_path / "raster_artifacts").rglob("marking_mask.png"))
    mask = cv2.imread(str(mask_file), cv2.IMREAD_UNCHANGED)
    mask[:10, :20] = 255 - mask[:10, :20]  # repaint 200 px of that tile
    cv2.imwrite(str(mask_file), mask)
    compute(ctx)
    v2 = open_map(tmp_path / "maps" / "city", 2)
    log = read_changelog(v2.path, v2.manifest)
    assert log["markings"]["total_px_changed"] == 200
    [tile] = log["markings"]["tiles"]
    assert tile["px_changed"] == 200 and tile["tile"] in ([0, 0], [0, 1], [0, 2])  # the rasters' tiles (0, 0..2)
    # per 10 m cell against the rasters' noise: the repainted 10 m x 5 m block is one changed cell (its tile's
    # north-west cell), the painted line's other cells unchanged
    [cell] = log["markings"]["cells"]
    assert cell["cell"] == [0, 10 * tile["tile"][1] + 9] and cell["px_changed"] == 200 and cell["p_value"] < 1e-6
    assert log["markings"]["test"]["cells_compared"] == 31 and log["markings"]["cell_m"] == 10.0


def test_diff_refuses_two_frames_with_one_line_naming_both_origins(tmp_path, monkeypatch):
    import os
    import subprocess
    import sys
    from pathlib import Path

    xy, dirs, _ = building_corners(buildings())
    compute(city_context(tmp_path, corner_table(xy, dirs, seed=1), rasters=False))
    from stages.common.geodesy import EnuOrigin
    from tests.stages.tiles import tiles_synth

    monkeypatch.setattr(tiles_synth, "ORIGIN", EnuOrigin(ORIGIN.lat_deg + 0.0003, ORIGIN.lon_deg, ORIGIN.h_m))  # 33 m N
    compute(city_context(tmp_path, corner_table(xy, dirs, seed=2), rasters=False, fingerprint="fp2"))
    d = tmp_path / "maps" / "city"
    log = read_changelog(open_map(d, 2).path, open_map(d, 2).manifest)
    assert log["frame"]["unchanged"] is False and log["corners"]["kept"] == 0
    repo = Path(__file__).resolve().parents[3]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, "-m", "mapservice", "tiles", "diff", "v1", "v2", "--root", str(tmp_path),
                          "--map", "city"], capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 1 and res.stdout == ""
    msg = [s for s in res.stderr.splitlines() if s.strip()]
    assert len(msg) == 1 and "different frames" in msg[0] and "Traceback" not in res.stderr
    assert f"{ORIGIN.lat_deg:.9f}" in msg[0] and f"{ORIGIN.lat_deg + 0.0003:.9f}" in msg[0]
