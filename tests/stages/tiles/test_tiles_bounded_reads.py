"""Bounded reading of what a version holds: an image or a table is checked against the manifest (and hard limits)
before it is decoded; `tiles verify` compares each file's size with the manifest's ``bytes``; radius queries accept
an unbounded radius and refuse NaN or negative ones. On a synthetic published map (no build)."""
from __future__ import annotations

import hashlib
import json
import shutil
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mapformat.layers import MAX_TILE_PIXELS, decode_png
from mapformat.loader import open_map
from mapformat.verify import verify_map
from pipeline.errors import LimitError, MapFormatError
from pipeline.versioned import write_latest
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import building_corners, buildings, city_context, corner_table


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bounded")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=4)))
    return root / "maps" / "city"


def png_bomb(width: int, height: int) -> bytes:
    """A valid 8-bit grey PNG of zeros: a few MB that decode to width x height bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + (zlib.crc32(kind + data) & 0xFFFFFFFF).to_bytes(4, "big")

    z = zlib.compressobj(1)
    block = (b"\0" * (width + 1)) * 100
    idat = b"".join([z.compress(block) for _ in range(height // 100)] + [z.flush()])
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def tampered(published: Path, tmp_path: Path, edit) -> tuple[Path, dict]:
    """A copy of the map whose v0001 ``edit(version_dir, manifest)`` changed, with the manifest's file table and
    LATEST's digest made to match (someone who can write the whole map)."""
    mdir = tmp_path / "maps" / "city"
    shutil.copytree(published, mdir)
    vdir = mdir / "v0001"
    manifest = json.loads((vdir / "manifest.json").read_text())
    edit(vdir, manifest)
    (vdir / "manifest.json").write_text(json.dumps(manifest, indent=1))
    write_latest(mdir, 1, durable=False)
    return mdir, manifest


def _replace(vdir: Path, manifest: dict, rel: str, data: bytes) -> None:
    (vdir / rel).write_bytes(data)
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}


def test_a_png_bomb_mask_is_refused_from_its_header(published, tmp_path):
    tile = {}

    def bomb(vdir: Path, manifest: dict) -> None:
        tile.update(next(t for t in manifest["tiles"] if t.get("marking")))
        _replace(vdir, manifest, f"{tile['dir']}/{tile['marking']['mask_file']}", png_bomb(30000, 30000))

    mdir, _ = tampered(published, tmp_path, bomb)
    reader = open_map(mdir)
    with pytest.raises(MapFormatError, match="PNG of 30000 x 30000 pixels; the manifest records"):
        reader.tile_marking(tile["i"], tile["j"])
    with pytest.raises(MapFormatError, match="30000 x 30000"):
        reader.tile_layer(tile["i"], tile["j"], "marking_mask")


def test_png_limits_hold_without_a_recorded_size():
    with pytest.raises(MapFormatError, match="beyond the limits"):
        decode_png(png_bomb(9000, 9000), Path("x.png"))  # 81 M pixels > MAX_TILE_PIXELS
    assert 9000 * 9000 > MAX_TILE_PIXELS
    with pytest.raises(MapFormatError, match="not a PNG"):
        decode_png(b"GIF89a" + b"\0" * 40, Path("x.png"))
    assert decode_png(png_bomb(300, 200), Path("x.png")).shape == (200, 300)


def test_a_corners_table_with_more_rows_than_the_manifest_records_is_refused(published, tmp_path):
    tile = {}

    def inflate(vdir: Path, manifest: dict) -> None:
        tile.update(next(t for t in manifest["tiles"] if t.get("n_corners")))
        rel = f"{tile['dir']}/corners.parquet"
        table = pq.read_table(vdir / rel)
        big = pa.concat_tables([table] * 1000)
        sink = pa.BufferOutputStream()
        pq.write_table(big, sink)
        _replace(vdir, manifest, rel, sink.getvalue().to_pybytes())

    mdir, _ = tampered(published, tmp_path, inflate)
    with pytest.raises(MapFormatError, match=f"rows, .* the manifest records {tile['n_corners']} rows for it"):
        open_map(mdir).tile_corners(tile["i"], tile["j"])


def test_vector_markings_are_read_verified(published, tmp_path):
    from mapformat.vectors import MARKINGS_FILE, read_map_features
    from pipeline.errors import IntegrityError

    reader = open_map(published)
    entries = [reader.tile_entry(*k) for k in reader.tile_keys()]
    assert read_map_features(reader.path, entries)  # the synthetic city's painted line
    rel = next(f"{e['dir']}/{MARKINGS_FILE}" for e in entries if MARKINGS_FILE in (e.get("files") or {}))

    def swap(vdir: Path, manifest: dict) -> None:  # another table in its place, the manifest left alone
        table = pq.read_table(vdir / rel)
        pq.write_table(pa.concat_tables([table, table]), vdir / rel)

    mdir, _ = tampered(published, tmp_path, swap)
    with pytest.raises(IntegrityError):
        read_map_features(mdir / "v0001", entries)


def test_verify_compares_each_files_size_with_the_manifest(published, tmp_path):
    def wrong_bytes(vdir: Path, manifest: dict) -> None:
        rel = next(r for r in manifest["files"] if r.endswith("corners.parquet"))
        manifest["files"][rel]["bytes"] += 1

    mdir, _ = tampered(published, tmp_path, wrong_bytes)
    problems = verify_map(mdir / "v0001")
    assert len(problems) == 1 and "bytes, the manifest records" in problems[0], problems
    assert verify_map(published / "v0001") == []


def test_radius_queries_accept_inf_and_refuse_nan_or_negative(published):
    reader = open_map(published)
    every = reader.all_corners().num_rows
    assert every > 0 and reader.corners_within(0.0, 0.0, float("inf")).num_rows == every
    assert reader.corners_within(1e6, -1e6, np.inf).num_rows == every
    assert reader.corners_in_bbox(-np.inf, -np.inf, np.inf, np.inf).num_rows == every
    assert reader.corners_in_bbox(-np.inf, -np.inf, 0.0, np.inf).num_rows == int(
        (reader.all_corners()["east_m"].to_numpy() < 0.0).sum())
    for radius in (float("nan"), -1.0):
        with pytest.raises(LimitError, match="radius"):
            reader.corners_within(0.0, 0.0, radius)
    with pytest.raises(LimitError):
        reader.corners_in_bbox(float("nan"), 0.0, 1.0, 1.0)
