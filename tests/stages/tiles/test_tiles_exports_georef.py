"""Exports opened with the libraries their users use: rasterio for the GeoTIFFs, pyproj for the frames."""
from __future__ import annotations

import json

import numpy as np
import pyproj
import pytest

from mapformat.export import export_map
from mapformat.geotiff import local_tm_crs
from mapformat.layers import local_tm_proj4
from mapformat.loader import open_map
from stages.common.geodesy import enu_to_geodetic
from stages.common.im2016_text import parse_frame_header, parse_im2016_text
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import (
    CELL_M,
    LINE_EAST_M,
    ORIGIN,
    TILE_M,
    building_corners,
    buildings,
    city_context,
    corner_table,
)

rasterio = pytest.importorskip("rasterio")


@pytest.fixture(scope="module")
def city_map(tmp_path_factory):
    root = tmp_path_factory.mktemp("georef")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=3)))
    return open_map(root / "maps" / "city")


def test_local_tm_keeps_the_enu_grid_within_a_tenth_of_a_millimetre():
    enu = np.array([[x, y, 0.0] for x in (-1000.0, -300.0, 0.0, 450.0, 1000.0) for y in (-1000.0, 0.0, 1000.0)])
    llh = enu_to_geodetic(enu, ORIGIN)
    tm = pyproj.Transformer.from_crs("EPSG:4326", pyproj.CRS.from_proj4(local_tm_proj4(ORIGIN.as_dict())),
                                     always_xy=True)
    x, y = tm.transform(llh[:, 1], llh[:, 0])
    assert np.abs(np.column_stack([x, y]) - enu[:, :2]).max() < 1e-4


def test_the_geotiff_crs_is_the_local_tm_on_the_wgs84_datum_by_name():
    """Same projection as the PROJ string (to 0.01 mm over +-1 km), but a named datum (not 'unknown based on the
    WGS 84 ellipsoid')."""
    crs = local_tm_crs(ORIGIN.as_dict())
    assert crs.datum.name == "World Geodetic System 1984 ensemble" or crs.datum.name == "World Geodetic System 1984"
    assert crs.geodetic_crs.to_epsg() == 4326
    assert [a.unit_name for a in crs.axis_info] == ["metre", "metre"]
    assert [a.direction for a in crs.axis_info] == ["east", "north"]
    lon, lat = np.meshgrid(ORIGIN.lon_deg + np.linspace(-0.01, 0.01, 5), ORIGIN.lat_deg + np.linspace(-0.01, 0.01, 5))
    a = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon.ravel(), lat.ravel())
    b = pyproj.Transformer.from_crs("EPSG:4326", pyproj.CRS.from_proj4(local_tm_proj4(ORIGIN.as_dict())),
                                    always_xy=True).transform(lon.ravel(), lat.ravel())
    assert np.abs(np.array(a) - np.array(b)).max() < 1e-5


def test_every_layer_is_a_cog_with_crs_bounds_nodata_and_description(city_map, tmp_path):
    files = [p for p in export_map(city_map, "geotiff", tmp_path / "tif") if p.suffix == ".tif"]
    loc = [p for p in files if p.parent.name.startswith("localizability_")]
    files = [p for p in files if p not in loc]
    crs = local_tm_crs(ORIGIN.as_dict())
    assert {p.parent.name for p in loc} == {"localizability_ekf", "localizability_mcl"}
    for path in loc:  # one 10 m pixel per cell of each tile the drive crossed (the drive crosses all 9 tiles)
        i, j = (int(k) for k in path.stem.split("_"))
        with rasterio.open(path) as ds:
            assert pyproj.CRS.from_wkt(ds.crs.to_wkt()).equals(crs, ignore_axis_order=True)
            assert ds.bounds == pytest.approx((i * TILE_M, j * TILE_M, (i + 1) * TILE_M, (j + 1) * TILE_M))
            assert ds.res == (10.0, 10.0) and np.isnan(ds.nodata) and ds.descriptions[0].startswith(path.parent.name)
    assert len(loc) == 2 * 9
    layers = {p.parent.name for p in files}
    assert layers == {"marking_mask", "traversable_mask", "intensity", "elevation_min", "elevation_mean",
                      "point_count"}
    assert len(files) == 6 * 3  # tiles (0, 0..2)
    crs = local_tm_crs(ORIGIN.as_dict())
    for path in files:
        i, j = (int(k) for k in path.stem.split("_"))
        with rasterio.open(path) as ds:
            assert ds.driver == "GTiff" and ds.profile.get("tiled")
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"  # GDAL's COG driver wrote it
            read = pyproj.CRS.from_wkt(ds.crs.to_wkt())  # what GDAL reads back from the GeoTIFF keys
            assert read.equals(crs, ignore_axis_order=True), read.to_wkt()
            assert "World Geodetic System 1984" in read.datum.name and "nknown" not in read.datum.name
            assert ds.bounds == pytest.approx((i * TILE_M, j * TILE_M, (i + 1) * TILE_M, (j + 1) * TILE_M))
            assert ds.res == (CELL_M, CELL_M) and ds.descriptions[0].startswith(path.parent.name)
            data = ds.read(1)
            want = city_map.tile_layer(i, j, path.parent.name)
            if path.parent.name == "intensity":
                assert np.isnan(ds.nodata)
                np.testing.assert_allclose(data, want, rtol=1e-6)
            if path.parent.name == "marking_mask":
                # the painted line lands at the pixel whose centre is at east = LINE_EAST_M (+- half a cell)
                cols = np.flatnonzero(data.any(axis=0))
                east = [ds.xy(0, c)[0] for c in cols]
                assert np.allclose(east, LINE_EAST_M, atol=CELL_M / 2 + 1e-9)
                np.testing.assert_array_equal(data, want)


def test_a_pixel_centre_maps_back_to_its_enu_point_on_earth(city_map, tmp_path):
    """The pixel whose centre is a known ENU point: GeoTIFF transform + CRS -> lat/lon (pyproj) equals the ENU
    point's lat/lon by pymap3d within 1 cm."""
    import pymap3d

    export_map(city_map, "geotiff", tmp_path / "tif")
    east, north = LINE_EAST_M, 150.25  # a pixel centre of tile (0, 1) (0.5 m cells from 0)
    with rasterio.open(tmp_path / "tif" / "marking_mask" / "0_1.tif") as ds:
        row, col = ds.index(east, north)
        x, y = ds.xy(row, col)  # the pixel centre, in the file's CRS
        assert ds.read(1)[row, col] == 255  # the painted line is there
        lon, lat = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(ds.crs.to_wkt()), "EPSG:4326",
                                               always_xy=True).transform(x, y)
    lat0, lon0, _ = pymap3d.enu2geodetic(east, north, 0.0, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m)
    e, n, _ = pymap3d.geodetic2enu(lat, lon, ORIGIN.h_m, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m)
    assert abs(e - east) < 0.01 and abs(n - north) < 0.01
    assert abs(lat - lat0) * 111_000 < 0.01 and abs(lon - lon0) * 88_000 < 0.01


def test_a_vrt_per_layer_reads_the_pixels_of_its_tiles(city_map, tmp_path):
    files = export_map(city_map, "geotiff", tmp_path / "tif")
    vrts = sorted(p for p in files if p.suffix == ".vrt" and not p.stem.startswith("localizability_"))
    assert [p.stem for p in vrts] == sorted(["marking_mask", "traversable_mask", "intensity", "elevation_min",
                                             "elevation_mean", "point_count"])
    for vrt in vrts:
        with rasterio.open(vrt) as mosaic:
            assert mosaic.driver == "VRT" and mosaic.crs == rasterio.open(tmp_path / "tif" / vrt.stem / "0_0.tif").crs
            assert mosaic.bounds == pytest.approx((0.0, 0.0, TILE_M, 3 * TILE_M))
            whole = mosaic.read(1)
            for j in range(3):
                with rasterio.open(tmp_path / "tif" / vrt.stem / f"0_{j}.tif") as tile:
                    r0, c0 = mosaic.index(tile.bounds.left + CELL_M / 2, tile.bounds.top - CELL_M / 2)
                    got = whole[r0:r0 + tile.height, c0:c0 + tile.width]
                    np.testing.assert_array_equal(got, tile.read(1))
                    assert mosaic.nodata == tile.nodata or (np.isnan(mosaic.nodata) and np.isnan(tile.nodata))


def test_loader_serves_any_layer(city_map):
    assert city_map.tile_layer(0, 1, "point_count").max() == 3
    assert np.nanmax(city_map.tile_layer(0, 1, "intensity")) <= 100
    np.testing.assert_array_equal(city_map.tile_layer(0, 1, "marking_mask"), city_map.tile_marking(0, 1))
    from pipeline.errors import CornermapError

    with pytest.raises(CornermapError, match="no raster layer 'nope'"):
        city_map.tile_layer(0, 1, "nope")


def test_im2016_text_names_its_origin_and_geojson_its_crs(city_map, tmp_path):
    export_map(city_map, "im2016-text", tmp_path / "c.txt")
    text = (tmp_path / "c.txt").read_text()
    assert parse_frame_header(text) == pytest.approx({"lat_deg": ORIGIN.lat_deg, "lon_deg": ORIGIN.lon_deg,
                                                      "h_m": ORIGIN.h_m})
    assert "# frame: local ENU" in text and "# units:" in text
    assert len(parse_im2016_text(text)["corner_id"]) == city_map.all_corners().num_rows
    export_map(city_map, "geojson", tmp_path / "c.geojson")
    doc = json.loads((tmp_path / "c.geojson").read_text())
    assert pyproj.CRS(doc["crs"]["properties"]["name"]).equals(pyproj.CRS("OGC:CRS84"))


def test_markings_geojson_puts_the_painted_line_on_earth(city_map, tmp_path):
    export_map(city_map, "markings-geojson", tmp_path / "m.geojson")
    doc = json.loads((tmp_path / "m.geojson").read_text())
    assert doc["crs"]["properties"]["name"].endswith("CRS84")
    lines = [f for f in doc["features"] if f["properties"]["type"] == "lane_solid"]
    assert len(lines) == 3  # the line crosses tiles (0, 0..2): one clipped piece per tile
    from stages.common.geodesy import geodetic_to_enu

    for f in lines:
        lon, lat = np.array(f["geometry"]["coordinates"]).T
        enu = geodetic_to_enu(lat, lon, np.full(len(lat), ORIGIN.h_m), ORIGIN)
        np.testing.assert_allclose(enu[:, 0], LINE_EAST_M, atol=0.05)


def test_trajectory_exports_state_their_frame_and_read_in_evo(city_map, tmp_path):
    """tiles export -f tum / -f kitti: the version's 3-D trajectories, read back by evo's own readers."""
    evo_io = pytest.importorskip("evo.tools.file_interface")
    from mapformat.trajectories import poses_matrices, read_version_trajectory
    from stages.common.trajectory_frame import read_trajectory_origin

    stamps, poses = read_version_trajectory(city_map, "drive_a")
    want = poses_matrices(poses)
    [tum] = export_map(city_map, "tum", tmp_path / "tum")
    head = [ln for ln in tum.read_text().splitlines() if ln.startswith("#")]
    assert any(ln.startswith("# attitude: 3-D") for ln in head) and any("frame: ENU" in ln for ln in head)
    assert read_trajectory_origin(tum) == ORIGIN
    traj = evo_io.read_tum_trajectory_file(str(tum))
    np.testing.assert_allclose(traj.poses_se3, want, atol=2e-6)
    np.testing.assert_allclose(traj.timestamps, stamps * 1e-9, rtol=0, atol=1e-6)
    kitti, times, side = export_map(city_map, "kitti", tmp_path / "kitti")
    assert (kitti.name, times.name, side.name) == ("drive_a.kitti.txt", "drive_a.times.txt",
                                                   "drive_a.kitti.frame.json")
    np.testing.assert_allclose(evo_io.read_kitti_poses_file(str(kitti)).poses_se3, want, atol=1e-6)
    from mapformat.trajectories import parse_tum_stamps_ns

    assert parse_tum_stamps_ns(times.read_text().split()).tolist() == stamps.tolist()  # exact to the ns
    assert read_trajectory_origin(kitti) == ORIGIN and json.loads(side.read_text())["n_poses"] == len(stamps)


def test_a_changed_trajectory_file_is_refused(city_map, tmp_path):
    import shutil

    from mapformat.loader import open_map as reopen
    from pipeline.errors import MapFormatError

    copy = tmp_path / "maps" / "city"
    shutil.copytree(city_map.path.parent, copy)
    version = copy / city_map.path.name
    traj = version / "trajectories" / "drive_a.tum"
    traj.write_text(traj.read_text().replace("50.000000", "50.100000", 1))
    with pytest.raises(MapFormatError, match="sha256 differs"):
        export_map(reopen(version), "tum", tmp_path / "out")
