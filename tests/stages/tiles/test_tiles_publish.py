"""tiles compute: publish a synthetic city, read it back, republish, quality gates, format refusal, verify."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mapformat.loader import open_map
from mapformat.verify import verify_map
from pipeline.errors import DataQualityError, MapFormatError
from pipeline.versioned import list_versions, read_latest, read_manifest
from stages.common.records import Trajectory
from stages.tiles.compute import compute
from stages.tiles.decl import STAGE
from stages.tiles.params import TilesParams
from tests.stages.tiles.tiles_synth import ORIGIN, building_corners, buildings, city_context, corner_table, drive_path


@pytest.fixture()
def city(tmp_path):
    xy, dirs, _ = building_corners(buildings())
    return tmp_path, corner_table(xy, dirs, seed=1)


def _publish(root, corners, **kw):
    return compute(city_context(root, corners, **kw))["published"].to_pylist()[0]


def test_publish_writes_a_complete_documented_version(city):
    root, corners = city
    row = _publish(root, corners)
    assert (row["map_name"], row["version"], row["n_corners"]) == ("city", 1, corners.num_rows)
    vdir = root / "maps" / "city" / "v0001"
    assert row["path"] == "maps/city/v0001" and read_latest(vdir.parent) == 1  # relative to the root
    m, sha = read_manifest(vdir)
    assert sha == row["manifest_sha256"]
    assert (m["format"], m["format_version"], m["tile_size_m"]) == ("cornermap-tiles", 1, 100.0)
    assert m["enu_origin"]["lat_deg"] == ORIGIN.lat_deg and m["enu_origin"]["ellipsoid"] == "WGS84"
    assert row["n_tiles"] == m["n_tiles"] == 9  # 3 x 3 tiles of 100 m over the 300 m city
    assert sum(t["n_corners"] for t in m["tiles"]) == corners.num_rows
    t00 = next(t for t in m["tiles"] if (t["i"], t["j"]) == (0, 0))
    assert t00["bounds_m"] == [0.0, 0.0, 100.0, 100.0]
    assert set(t00["files"]) == {"corners.parquet", "marking_mask.png", "traversable_mask.png", "intensity.png",
                                 "elevation_min.png", "elevation_mean.png", "point_count.png", "raster.json",
                                 "markings.parquet", "localizability.parquet"}
    vec = pq.read_table(vdir / "tiles" / "0_0" / "markings.parquet").to_pylist()  # the painted line, clipped
    assert [(v["type"], v["geometry"]) for v in vec] == [("lane_solid", "LineString")] and t00[
        "n_marking_features"
    ] == 1
    np.testing.assert_allclose(vec[0]["east_m"], 50.25, atol=0.05)
    assert sorted(vec[0]["north_m"])[0] == 0.0 and sorted(vec[0]["north_m"])[-1] == 100.0
    assert t00["marking"]["mask_file"] == "marking_mask.png"
    assert t00["n_marking_px"] == 200 and t00["marking"]["cell_m"] == 0.5
    assert m["inputs"]["corner_map"] == {"dataset": "corner_map", "fingerprint": "fp1-corner_map"}
    assert m["params"]["tile_size_m"] == 100.0 and m["code_version"] == STAGE.code_version
    assert m["source_drives"][0]["drive"] == "drive_a" and m["source_drives"][0]["fingerprint"]
    truth = Trajectory.from_tum(vdir / m["source_drives"][0]["trajectory"])
    stamps_s, T = truth.stamp_s, truth.T
    path = drive_path()
    np.testing.assert_allclose(T[:, :2, 3], path, atol=1e-6)
    assert stamps_s[1] - stamps_s[0] == pytest.approx(0.1, abs=1e-6)
    assert m["quality"]["corners_per_km"] > 100 and m["quality"]["empty_path_tile_share"] == 0.0
    assert verify_map(vdir) == []


def test_read_back_every_corner_exactly(city):
    root, corners = city
    _publish(root, corners)
    got = open_map(root / "maps" / "city").all_corners().sort_by("corner_id")
    assert got.equals(corners.sort_by("corner_id"))


def test_republish_same_inputs_is_a_noop_and_changed_inputs_make_v2(city):
    root, corners = city
    assert _publish(root, corners)["version"] == 1
    again = _publish(root, corners)
    assert again["version"] == 1 and list_versions(root / "maps" / "city") == [1]
    v2 = _publish(root, corners.slice(0, corners.num_rows - 4), fingerprint="fp2")
    assert v2["version"] == 2 and v2["n_corners"] == corners.num_rows - 4
    m, _ = read_manifest(root / "maps" / "city" / "v0002")
    assert m["parent_version"] == 1 and open_map(root / "maps" / "city", "v1").version == 1
    assert _publish(root, corners, fingerprint="fp2", params=TilesParams(keep_last=1))["version"] == 3
    assert list_versions(root / "maps" / "city") == [3]


def test_failed_density_gate_exits_3_and_latest_unchanged(city):
    root, corners = city
    _publish(root, corners)
    sparse = corners.slice(0, 8)  # 8 corners, all in tile (0, 0): too few per km, empty path tiles
    with pytest.raises(DataQualityError, match="corners/km") as info:
        _publish(root, sparse, fingerprint="fp9")
    assert info.value.exit_code == 3 and "hold no corner" in str(info.value)
    assert read_latest(root / "maps" / "city") == 1 and list_versions(root / "maps" / "city") == [1]
    loose = TilesParams(min_corners_per_km=1.0, max_empty_path_tile_share=1.0)
    assert _publish(root, sparse, fingerprint="fp9", params=loose)["version"] == 2


def test_schema_gate_lists_bad_columns_and_values(city):
    root, corners = city
    bad = corners.set_column(corners.schema.get_field_index("n_obs"), "n_obs", pa.array(
        np.full(corners.num_rows, 3.0))).drop_columns(["convex"])
    with pytest.raises(DataQualityError) as info:
        _publish(root, bad)
    assert "'n_obs' is double, expected int64" in str(info.value) and "'convex' missing" in str(info.value)
    cov = corners["cov_en_m2"].to_numpy().copy()
    cov[3] = 1.0  # |en| > sqrt(ee*nn): not PSD
    ids = corners["corner_id"].to_numpy().copy()
    ids[5] = ids[6]
    bad2 = corners.set_column(corners.schema.get_field_index("cov_en_m2"), corners.schema.field("cov_en_m2"),
                              pa.array(cov)).set_column(0, corners.schema.field("corner_id"), pa.array(ids))
    with pytest.raises(DataQualityError) as info:
        _publish(root, bad2)
    assert "positive semi-definite" in str(info.value) and "not unique" in str(info.value)
    assert read_latest(root / "maps" / "city") is None


def test_raster_origin_off_the_tile_grid_is_rejected(city):
    root, corners = city
    ctx = city_context(root, corners, params=TilesParams(tile_size_m=50.0))
    with pytest.raises(DataQualityError, match="same tile_size_m"):
        compute(ctx)


def test_unknown_format_version_is_refused(city, tmp_path):
    root, corners = city
    _publish(root, corners)
    copy = tmp_path / "future"
    shutil.copytree(root / "maps" / "city" / "v0001", copy)
    m = json.loads((copy / "manifest.json").read_text())
    m["format_version"] = 99
    (copy / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(MapFormatError, match="version 99 is not readable"):
        open_map(copy)
    assert verify_map(copy) and "version 99" in verify_map(copy)[0]


def test_verify_detects_a_flipped_byte_in_a_tile(city):
    root, corners = city
    _publish(root, corners)
    vdir = root / "maps" / "city" / "v0001"
    target = vdir / "tiles" / "1_1" / "corners.parquet"
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x40
    target.write_bytes(bytes(data))
    problems = verify_map(vdir)
    assert len(problems) == 1 and "tiles/1_1/corners.parquet" in problems[0] and "sha256" in problems[0]


def test_flat_prefixed_raster_artifacts_are_copied_per_tile(city):
    root, corners = city
    _publish(root, corners, flat_rasters=True)
    reader = open_map(root / "maps" / "city")
    t = reader.tile_entry(0, 1)
    assert set(t["files"]) == {"corners.parquet", "marking.png", "intensity.png", "raster.json", "markings.parquet",
                                "localizability.parquet"}
    assert t["marking"]["mask_file"] == "marking.png" and reader.tile_marking(0, 1).sum() == 255 * 200
    assert "marking.png" not in reader.tile_entry(1, 1)["files"]  # another tile's files are not copied


def test_missing_raster_artifacts_fail_the_schema_gate(city):
    root, corners = city
    ctx = city_context(root, corners)
    ctx.inputs.artifact_dir = lambda arg, partition=None: root / "nowhere"
    with pytest.raises(DataQualityError, match="no marking mask"):
        compute(ctx)
