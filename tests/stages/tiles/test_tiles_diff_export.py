"""tiles diff (one building removed -> exactly its corners removed), exports (GeoJSON, Table 1 text, Autoware)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from mapformat.diff import count_changed_pixels, diff_maps, match_corners
from mapformat.export import export_map
from mapformat.loader import open_map
from stages.common.im2016_text import parse_im2016_text
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import ORIGIN, building_corners, buildings, city_context, corner_table

REMOVED_BUILDING = 14  # block (2, 2): its corners lie in tile (1, 1)


@pytest.fixture(scope="module")
def two_builds(tmp_path_factory):
    """Two builds of the same city (independent 5 mm noise, renumbered ids); the second lacks one building."""
    root = tmp_path_factory.mktemp("diff")
    xy, dirs, owner = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=11)))
    keep = owner != REMOVED_BUILDING
    compute(city_context(root, corner_table(xy[keep], dirs[keep], seed=12, first_id=1000), fingerprint="fp2"))
    d = root / "maps" / "city"
    return open_map(d, "v1"), open_map(d, "v2"), xy[owner == REMOVED_BUILDING], xy


def test_diff_reports_the_removed_building_and_nothing_else(two_builds):
    a, b, removed_xy, _ = two_builds
    diffs = diff_maps(a, b, move_threshold_m=0.1, match_radius_m=1.0)
    assert [(t.i, t.j) for t in diffs] == [(1, 1)]
    t = diffs[0]
    assert (t.corners_removed, t.corners_added, t.corners_moved, t.marking_px_changed) == (4, 0, 0, 0)
    got = a.all_corners()
    got_xy = np.column_stack([got["east_m"].to_numpy(), got["north_m"].to_numpy()])
    ids = got["corner_id"].to_numpy()
    removed_got = got_xy[np.isin(ids, t.removed_ids)]
    d = np.linalg.norm(removed_got[:, None, :] - removed_xy[None, :, :], axis=2)
    assert (d.min(axis=1) < 0.05).all()  # the removed corners are that building's vertices
    assert diff_maps(b, a) and diff_maps(b, a)[0].corners_added == 4
    assert diff_maps(a, a) == []


def test_diff_reports_moves_and_marking_changes():
    m = match_corners(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]]),
                      np.array([[0.3, 0.0], [10.0, 0.0], [50.0, 0.0]]), match_radius_m=1.0)
    assert m.ia.tolist() == [0, 1] and m.ib.tolist() == [0, 1] and m.dist_m[0] == pytest.approx(0.3)
    a = np.zeros((4, 4), np.uint8)
    b = a.copy()
    b[1, 1:3] = 255
    assert count_changed_pixels(a, b) == 2 and count_changed_pixels(None, b) == 2
    assert count_changed_pixels(a, None) == 0 and count_changed_pixels(None, None) == 0


def _ecef_to_enu(x, y, z):
    """Independent of pymap3d: pyproj ECEF + the textbook ENU rotation about ORIGIN."""
    from pyproj import Transformer

    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    x0, y0, z0 = to_ecef.transform(ORIGIN.lon_deg, ORIGIN.lat_deg, ORIGIN.h_m)
    lat, lon = np.radians(ORIGIN.lat_deg), np.radians(ORIGIN.lon_deg)
    R = np.array([[-np.sin(lon), np.cos(lon), 0],
                  [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
                  [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]])
    return (R @ np.vstack([x - x0, y - y0, z - z0])).T


def test_geojson_is_valid_wgs84_and_corners_lie_on_the_buildings(two_builds, tmp_path):
    a, _, _, truth_xy = two_builds
    out = tmp_path / "city.geojson"
    export_map(a, "geojson", out)
    doc = json.loads(out.read_text())
    assert doc["type"] == "FeatureCollection" and len(doc["features"]) == a.all_corners().num_rows
    coords = np.array([f["geometry"]["coordinates"] for f in doc["features"]])
    assert all(f["type"] == "Feature" and f["geometry"]["type"] == "Point" for f in doc["features"])
    lon, lat, h = coords.T
    assert ((-180 <= lon) & (lon <= 180) & (-90 <= lat) & (lat <= 90)).all()
    assert abs(lat.mean() - ORIGIN.lat_deg) < 0.01 and abs(lon.mean() - ORIGIN.lon_deg) < 0.01  # lon, lat order
    from pyproj import Transformer

    x, y, z = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(lon, lat, h)
    enu = _ecef_to_enu(np.asarray(x), np.asarray(y), np.asarray(z))
    corners = a.all_corners()
    by_id = {int(f["properties"]["corner_id"]): k for k, f in enumerate(doc["features"])}
    order = [by_id[int(i)] for i in corners["corner_id"].to_numpy()]
    exact = np.column_stack([corners["east_m"].to_numpy(), corners["north_m"].to_numpy()])
    assert np.abs(enu[order, :2] - exact).max() < 1e-3  # round trip to ENU within 1 mm
    d = np.linalg.norm(enu[:, None, :2] - truth_xy[None, :, :], axis=2).min(axis=1)
    assert (d < 0.05).all()  # every exported corner lies on a building vertex


def test_im2016_text_round_trip(two_builds, tmp_path):
    a = two_builds[0]
    out = tmp_path / "corners.txt"
    export_map(a, "im2016-text", out)
    text = out.read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("# ") or ln.startswith("# Index")]
    assert lines[0].startswith("# Index\tEast (m)") and len(lines[1].split("\t")) == 9
    cols = parse_im2016_text(text, source=str(out))
    c = a.all_corners()
    np.testing.assert_array_equal(cols["corner_id"], c["corner_id"].to_numpy())
    np.testing.assert_allclose(cols["east_m"], c["east_m"].to_numpy(), atol=5e-4)
    np.testing.assert_allclose(np.degrees(cols["theta1_rad"]), np.degrees(c["theta1_rad"].to_numpy()), atol=5e-3)
    np.testing.assert_allclose(cols["cov_en_m2"], c["cov_en_m2"].to_numpy(), rtol=1e-2)


def test_autoware_export_without_the_build_datasets_names_what_is_missing(two_builds, tmp_path):
    from pipeline.errors import DatasetIOError

    with pytest.raises(DatasetIOError, match="recorded but not committed under .*removed by gc"):
        export_map(two_builds[0], "autoware", tmp_path / "aw", root=tmp_path)


def test_autoware_metadata_and_lanelet2_documents():
    import xml.etree.ElementTree as ET

    from mapformat.autoware import lanelet2_osm, pointcloud_metadata_yaml
    from stages.common.geodesy import geodetic_to_enu
    from stages.common.marking_vectors import MarkingFeature

    meta = yaml.safe_load(pointcloud_metadata_yaml([(0, -1), (-2, 3)], 20.0))
    assert meta == {"x_resolution": 20, "y_resolution": 20, "0_-1.pcd": [0, -20], "-2_3.pcd": [-40, 60]}
    feats = [MarkingFeature("lane_dashed", np.array([[10.0, 5.0], [40.0, 5.0]]), 0.15, 30.0),
             MarkingFeature("crosswalk", np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 9.0], [0.0, 9.0]]), 4.0, 9.0),
             MarkingFeature("arrow", np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0]]), 0.7, 5.0)]
    root = ET.fromstring(lanelet2_osm(feats, ORIGIN))
    ways = root.findall("way")
    assert [{t.get("k"): t.get("v") for t in w.findall("tag")}["type"] for w in ways] == ["line_thin",
                                                                                        "crosswalk_polygon"]
    refs = [nd.get("ref") for nd in ways[1].findall("nd")]
    assert len(refs) == 5 and refs[0] == refs[-1]  # a closed area
    for node in root.findall("node"):
        tags = {t.get("k"): float(t.get("v")) for t in node.findall("tag")}
        enu = geodetic_to_enu(float(node.get("lat")), float(node.get("lon")), ORIGIN.h_m, ORIGIN)[0]
        assert abs(enu[0] - tags["local_x"]) < 1e-3 and abs(enu[1] - tags["local_y"]) < 1e-3


def test_im2016_text_malformed_lines_name_the_line():
    from pipeline.errors import FormatError

    good = "# header\n1\t10.000\t10.000\t132.00\t45.00\t2.10e-03\t9.00e-04\t9.00e-04\t2.90e-03\n"
    assert parse_im2016_text(good)["corner_id"].tolist() == [1]
    with pytest.raises(FormatError, match="line 2: expected 9 fields"):
        parse_im2016_text("# h\n1\t2\t3\n")
    with pytest.raises(FormatError, match="line 2: not a number"):
        parse_im2016_text(good.replace("132.00", "abc"))
    with pytest.raises(FormatError, match="not symmetric"):
        parse_im2016_text(good.replace("9.00e-04\t2.90e-03", "1.00e-04\t2.90e-03"))


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_folder_export_never_mixes_with_or_half_replaces_an_existing_folder(two_builds, tmp_path):
    from mapformat.export import ExportTargetError
    from pipeline.errors import DatasetIOError

    v1, v2 = two_builds[0], two_builds[1]
    out = tmp_path / "rasters"
    export_map(v1, "geotiff", out)
    before = _tree(out)
    with pytest.raises(ExportTargetError, match=r"rasters: a folder holding \d+ entries; .*--overwrite"):
        export_map(v2, "geotiff", out)
    assert _tree(out) == before
    (out / "stale.tif").write_bytes(b"an earlier export's file")
    files = export_map(v2, "geotiff", out, overwrite=True)
    export_map(v2, "geotiff", tmp_path / "fresh")
    assert _tree(out) == _tree(tmp_path / "fresh") != before  # replaced whole: the stale file is gone
    assert sorted(files) == sorted(p for p in out.rglob("*") if p.is_file())
    # a failing export (the Autoware one needs build datasets this root does not hold) leaves the folder as it was
    replaced = _tree(out)
    with pytest.raises(DatasetIOError, match="recorded but not committed"):
        export_map(v2, "autoware", out, root=tmp_path, overwrite=True)
    assert _tree(out) == replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh", "rasters"]  # no staging folder left behind
