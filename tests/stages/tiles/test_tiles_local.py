"""Tile-local re-derivation: a tile the new version does not touch keeps its parent's bytes (stages/tiles/keep.py).

The synthetic city of ``tiles_synth`` (3 x 3 tiles of 100 m, drive_a along every north-south street); version 2 adds
drive_b along the street at east = 250 m only (tiles (2, *)), whose observations reach the corners east of 200 m.
The truth of which tiles it touches is known by construction.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest

from mapformat.loader import open_map
from mapformat.verify import verify_map
from pipeline.testing import make_context
from stages.tiles.compute import compute
from stages.tiles.params import TilesParams
from stages.tiles.tilelocal import Tolerances, changed_poses
from tests.stages.tiles.tiles_synth import (
    ORIGIN,
    TILE_M,
    building_corners,
    buildings,
    corner_table,
    drive_info_table,
    drive_path,
    poses_table,
    write_rasters,
)

B_EAST_M = 250.0  # drive_b's street


def _context(root, corners, drives: dict[str, np.ndarray], fingerprint: str, params=None):
    poses = pa.concat_tables([poses_table(xy, name) for name, xy in drives.items()])
    info = pa.concat_tables([drive_info_table(name) for name in drives])
    base = root / "raster_artifacts"
    tables = {"corner_map": corners, "poses": poses, "drive_info": info, "raster": write_rasters(base)}
    meta = {arg: {"fingerprint": f"{fingerprint}-{arg}"} for arg in [*tables, "rasters"]}
    meta["drive_info"]["enu_origin"] = ORIGIN.as_dict()
    ctx = make_context(
        "tiles",
        params or TilesParams(),
        tables,
        metadata=meta,
        input_artifacts={"rasters": base},
        settings={"map_name": "city", "root": str(root), "tile_size_m": TILE_M, "enu_origin": ORIGIN.as_dict()},
        outputs=("published",),
        workdir=root / "work",
    )
    ctx.inputs.artifact_dir = lambda arg, partition=None: base / partition.label
    return ctx


def _b_path() -> np.ndarray:
    n = np.arange(2.0, 298.0, 1.0)
    return np.column_stack([np.full(len(n), B_EAST_M), n])


def _tile_of(t: pa.Table) -> np.ndarray:
    return np.column_stack([np.floor(t["east_m"].to_numpy() / TILE_M), np.floor(t["north_m"].to_numpy() / TILE_M)])


def _v2_corners(v1: pa.Table, shift_m: dict[tuple[int, int], float]) -> pa.Table:
    """v1's corners as the corner map re-derives them after drive_b: those east of 200 m seen by drive_b too (more
    observations), every corner of tile ``key`` moved east by ``shift_m[key]``; ids renumbered (the tiles stage
    carries them)."""
    tiles = _tile_of(v1)
    east = v1["east_m"].to_numpy().copy()
    for (i, j), d in shift_m.items():
        east[(tiles[:, 0] == i) & (tiles[:, 1] == j)] += d
    seen_b = tiles[:, 0] == 2
    n_obs = v1["n_obs"].to_numpy() + np.where(seen_b, 7, 0)
    drives = ["drive_a,drive_b" if s else "drive_a" for s in seen_b]  # comma-separated, as the corner map
    out = v1.set_column(v1.schema.get_field_index("east_m"), "east_m", pa.array(east))
    out = out.set_column(out.schema.get_field_index("n_obs"), "n_obs", pa.array(n_obs, pa.int64()))
    out = out.set_column(out.schema.get_field_index("drives"), "drives", pa.array(drives, pa.string()))
    return out.set_column(0, "corner_id", pa.array(np.arange(500, 500 + out.num_rows), pa.int64()))


def _files(vdir) -> dict[tuple[int, int], dict[str, str]]:
    man = json.loads((vdir / "manifest.json").read_text())
    return {(t["i"], t["j"]): t["files"] for t in man["tiles"]}


@pytest.fixture(scope="module")
def two_versions(tmp_path_factory):
    """v1 from drive_a; v2 adds drive_b, with tile (1, 1)'s corners re-derived 0.02 m east (beyond the tolerance)
    and tile (0, 0)'s 0.002 m east (within it)."""
    root = tmp_path_factory.mktemp("tilelocal")
    xy, dirs, _ = building_corners(buildings())
    v1 = corner_table(xy, dirs, seed=1)
    compute(_context(root, v1, {"drive_a": drive_path()}, "fp1"))
    v2 = _v2_corners(v1, {(1, 1): 0.02, (0, 0): 0.002})
    out = compute(_context(root, v2, {"drive_a": drive_path(), "drive_b": _b_path()}, "fp2"))
    return root / "maps" / "city", v1, v2, out["_extra"]["outcome"][0]


def test_untouched_tiles_keep_their_sha256_and_touched_ones_change(two_versions):
    mdir, _, _, outcome = two_versions
    assert "(144 corners, 9 tiles, 5 kept from v0001)" in outcome
    f1, f2 = _files(mdir / "v0001"), _files(mdir / "v0002")
    touched = {(2, 0), (2, 1), (2, 2), (1, 1)}  # drive_b's path and observations; the 0.02 m move
    assert set(f1) == set(f2) == {(i, j) for i in range(3) for j in range(3)}
    for key in set(f1) - touched:
        assert f2[key] == f1[key], key  # every file, byte for byte (the manifest's sha256)
    for key in touched:
        assert f2[key]["corners.parquet"] != f1[key]["corners.parquet"], key
    man = json.loads((mdir / "v0002" / "manifest.json").read_text())
    rec = man["tile_local"]
    assert (rec["n_kept"], rec["n_rederived"]) == (5, 4)
    assert 0.0019 < rec["kept_corner_shift_max_m"] < 0.0021  # tile (0, 0)'s 2 mm, left unpublished


def test_mixed_version_verifies_and_the_loader_reads_each_tile_from_its_derivation(two_versions):
    mdir, v1, v2, _ = two_versions
    assert verify_map(mdir / "v0002") == []
    new, old = open_map(mdir, 2).all_corners(), open_map(mdir, 1).all_corners()
    assert new.num_rows == v2.num_rows and len(set(new["corner_id"].to_pylist())) == new.num_rows
    assert set(new["corner_id"].to_pylist()) == set(old["corner_id"].to_pylist())  # ids stable
    by_id = {r["corner_id"]: r for r in old.to_pylist()}
    kept_tile = _tile_of(new)
    for row, (i, j) in zip(new.to_pylist(), kept_tile.tolist()):
        was = by_id[row["corner_id"]]
        if (i, j) == (0, 0):  # kept: the published corner, not the re-derivation 2 mm east
            assert row["east_m"] == was["east_m"]
        elif (i, j) == (1, 1):
            assert row["east_m"] == pytest.approx(was["east_m"] + 0.02, abs=1e-9)
        elif i == 2:
            assert row["n_obs"] == was["n_obs"] + 7 and row["drives"] == "drive_a,drive_b"
    log = json.loads((mdir / "v0002" / "changelog.json").read_text())
    assert (log["corners"]["removed"], log["corners"]["added"], log["corners"]["kept"]) == ([], [], v1.num_rows)


def test_kept_files_are_linked_not_copied(two_versions):
    mdir, _, _, _ = two_versions
    a, b = mdir / "v0001" / "tiles" / "0_1" / "corners.parquet", mdir / "v0002" / "tiles" / "0_1" / "corners.parquet"
    assert a.stat().st_ino == b.stat().st_ino


def test_a_corner_crossing_a_tile_border_touches_both_tiles(tmp_path):
    """A corner 0.5 mm west of the border between tiles (0, 1) and (1, 1), re-derived 1 mm east (within the
    tolerance, but now in the other tile): both tiles are re-derived, the corner is published once with its id."""
    xy, dirs, _ = building_corners(buildings())
    v1 = corner_table(xy, dirs, seed=1)
    k = int(np.argmin(np.hypot(v1["east_m"].to_numpy() - 90.0, v1["north_m"].to_numpy() - 115.0)))
    east = v1["east_m"].to_numpy().copy()
    east[k] = 99.9995
    v1 = v1.set_column(1, "east_m", pa.array(east))
    compute(_context(tmp_path, v1, {"drive_a": drive_path()}, "fp1"))
    east[k] = 100.0005
    compute(_context(tmp_path, v1.set_column(1, "east_m", pa.array(east)), {"drive_a": drive_path()}, "fp2"))
    f1, f2 = _files(tmp_path / "maps/city/v0001"), _files(tmp_path / "maps/city/v0002")
    assert {key for key in f1 if f1[key] != f2[key]} == {(0, 1), (1, 1)}
    corners = open_map(tmp_path / "maps/city", 2).all_corners()
    assert sorted(corners["corner_id"].to_pylist()) == sorted(v1["corner_id"].to_pylist())
    assert verify_map(tmp_path / "maps/city/v0002") == []


def test_tile_local_off_rewrites_every_tile(tmp_path):
    xy, dirs, _ = building_corners(buildings())
    v1 = corner_table(xy, dirs, seed=1)
    compute(_context(tmp_path, v1, {"drive_a": drive_path()}, "fp1"))
    v2 = v1.set_column(1, "east_m", pa.array(v1["east_m"].to_numpy() + 0.001))
    compute(_context(tmp_path, v2, {"drive_a": drive_path()}, "fp2"))  # all within 1 mm: all kept
    compute(_context(tmp_path, v2, {"drive_a": drive_path()}, "fp3", TilesParams(tile_local=False)))
    f1, f2, f3 = (_files(tmp_path / f"maps/city/v000{n}") for n in (1, 2, 3))
    assert f2 == f1
    assert all(f3[k]["corners.parquet"] != f1[k]["corners.parquet"] for k in f1)  # every tile holds corners


def test_changed_poses_new_gone_and_moved_beyond_the_tolerance():
    tol = Tolerances(0.005, 0.1, 0.005, 25.0)
    stamps = np.arange(5, dtype=np.int64)
    poses = np.column_stack([np.arange(5.0), np.zeros((5, 5)), np.ones(5)])  # x, y, z, qx, qy, qz, qw
    turned = poses.copy()
    turned[3, 5:7] = [np.sin(0.0004 / 2), np.cos(0.0004 / 2)]  # 0.4 mrad: 10 mm at 25 m
    turned[4, 5:7] = [np.sin(0.0001 / 2), np.cos(0.0001 / 2)]  # 0.1 mrad: 2.5 mm at 25 m
    turned[2, 0] += 0.004  # 4 mm
    other = poses.copy()
    other[:, 1] += 100.0
    pts, within = changed_poses(
        {"a": (stamps, poses), "gone": (stamps, poses + 10)}, {"a": (stamps, turned), "b": (stamps, other)}, tol
    )
    expect = np.vstack([poses[3:4, :2], other[:, :2], poses[:, :2] + 10])  # a's pose 3, b's (new), gone's
    assert sorted(map(tuple, np.round(pts, 6))) == sorted(map(tuple, np.round(expect, 6)))
    assert within["a"] == pytest.approx(0.004, abs=1e-6)  # the largest move left within the tolerance


def test_tiles_verify_passes_on_the_mixed_version(two_versions):
    import typer
    from typer.testing import CliRunner

    from stages.tiles.cli import register

    mdir, _, _, _ = two_versions
    app = typer.Typer()
    register(app)
    res = CliRunner().invoke(app, ["tiles", "verify", "--all", "--root", str(mdir.parent.parent)])
    assert res.exit_code == 0 and "v0001: ok" in res.output and "v0002: ok" in res.output, res.output
