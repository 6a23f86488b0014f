"""The map format stands alone: its JSON documents conform to the JSON Schemas shipped in ``mapformat/schemas``
(checked with the ``jsonschema`` package, draft 2020-12) and its Parquet layers read with DuckDB, an engine that
shares no code with pyarrow's Python API. (Every version the suite publishes is also checked against the schemas
after each test: tests/conftest.py.)"""
from __future__ import annotations

import json

import numpy as np
import pytest

from mapformat.loader import open_map
from mapformat.schemas import NAMES, problems, schema, validate
from pipeline.errors import MapFormatError
from tests.stages.tiles.tiles_synth import publish_two_versions


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    return publish_two_versions(tmp_path_factory.mktemp("schemas")) / "maps" / "city"


def test_every_schema_is_a_valid_draft_2020_12_schema_shipped_with_the_package():
    from importlib import resources

    from jsonschema import Draft202012Validator

    for name in NAMES:
        assert resources.files("mapformat.schemas").joinpath(f"{name}.schema.json").is_file()
        doc = schema(name)
        assert doc["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        Draft202012Validator.check_schema(doc)


def test_published_manifest_and_changelog_conform_and_a_broken_one_is_named(published):
    for v in ("v0001", "v0002"):
        manifest = json.loads((published / v / "manifest.json").read_text())
        changelog = json.loads((published / v / "changelog.json").read_text())
        assert problems(manifest, "manifest") == [] and problems(changelog, "changelog") == []
    manifest["tiles"][0]["dir"] = "../../etc"
    manifest["files"]["tiles/0_0/corners.parquet"]["sha256"] = "xyz"
    del manifest["enu_origin"]["lat_deg"]
    found = problems(manifest, "manifest")
    assert len(found) == 3 and any(p.startswith("tiles/0/dir") for p in found) \
        and any(p.startswith("enu_origin: 'lat_deg'") for p in found), found
    with pytest.raises(MapFormatError, match=r"manifest\.json: does not conform to the manifest schema \(3 problem"):
        validate(manifest, "manifest", "v0002/manifest.json")


def test_identity_written_by_maps_create_conforms(tmp_path):
    from mapservice.maps import create_map

    ident = create_map(tmp_path, "kept", {"lat_deg": 37.5, "lon_deg": 127.0, "h_m": 40.0})
    doc = json.loads((tmp_path / "maps" / "kept" / "map.json").read_text())
    assert problems(doc, "map-identity") == [] and doc == ident.dump()
    doc["tile_size_m"] = -1
    doc["surprise"] = 1
    assert len(problems(doc, "map-identity")) == 2


def test_parquet_layers_read_with_duckdb_agree_with_the_manifest_and_the_loader(published):
    duckdb = pytest.importorskip("duckdb")
    vdir = published / "v0002"
    manifest = json.loads((vdir / "manifest.json").read_text())
    con = duckdb.connect()
    corners = con.execute(
        f"SELECT corner_id, east_m, north_m, cov_ee_m2, cov_en_m2, cov_nn_m2, filename "
        f"FROM read_parquet('{vdir}/tiles/*/corners.parquet', filename=true) ORDER BY corner_id").fetchall()
    assert len(corners) == manifest["n_corners"] == sum(t["n_corners"] for t in manifest["tiles"])
    loader = open_map(published, "v0002").all_corners().sort_by("corner_id")
    np.testing.assert_array_equal([c[0] for c in corners], loader["corner_id"].to_numpy())
    np.testing.assert_array_equal([c[1] for c in corners], loader["east_m"].to_numpy())
    size = manifest["tile_size_m"]
    for cid, e, n, ee, en, nn, fname in corners:  # each corner in its own tile's file, with a PSD covariance
        i, j = (int(k) for k in fname.replace("\\", "/").split("/")[-2].split("_"))
        assert i * size <= e < (i + 1) * size and j * size <= n < (j + 1) * size
        assert ee > 0 and nn > 0 and ee * nn - en * en > 0
    types = {r[0]: r[1] for r in con.execute(
        f"DESCRIBE SELECT * FROM read_parquet('{vdir}/tiles/0_0/corners.parquet')").fetchall()}
    assert types["corner_id"] == "BIGINT" and types["east_m"] == "DOUBLE" and types["convex"] == "BOOLEAN"
    assert list(types) == manifest["corner_columns"]
    vec = con.execute(f"SELECT type, geometry, len(east_m), width_m "
                      f"FROM read_parquet('{vdir}/tiles/*/markings.parquet')"
                      ).fetchall()
    assert len(vec) == sum(t.get("n_marking_features", 0) for t in manifest["tiles"]) and vec[0][:2] == (
        "lane_solid", "LineString")


def test_the_localizability_layer_reads_with_duckdb_with_its_units(published):
    duckdb = pytest.importorskip("duckdb")
    vdir = published / "v0002"
    manifest = json.loads((vdir / "manifest.json").read_text())
    con = duckdb.connect()
    rows = con.execute(f"SELECT method, count(*), median(sigma_2d_m), max(abs(sigma_2d_m - sqrt(cov_ee_m2 + "
                       f"cov_nn_m2))) FROM read_parquet('{vdir}/tiles/*/localizability.parquet') GROUP BY method "
                       "ORDER BY method").fetchall()
    assert [r[0] for r in rows] == ["ekf", "mcl"] and rows[0][1] == rows[1][1] == manifest["localizability"]["n_cells"]
    assert rows[0][2] == pytest.approx(manifest["localizability"]["methods"]["ekf"]["median_sigma_2d_m"], abs=1e-4)
    assert rows[0][3] < 1e-12
    meta = con.execute(f"SELECT key, value FROM parquet_kv_metadata('{vdir}/tiles/0_0/localizability.parquet')"
                       ).fetchall()
    assert any(k == b"ARROW:schema" for k, _ in meta)  # units travel in the file's Arrow field metadata
