"""The localizability layer in a published version: one file per tile the drive crosses, the manifest's summary,
the loader, the GeoTIFF export, and a version without it (older maps) read as before."""
from __future__ import annotations

import json

import numpy as np
import pyarrow.compute as pc
import pytest

from mapformat.loader import open_map
from mapformat.localizability import LOCALIZABILITY_FILE, SCHEMA
from stages.tiles.compute import compute
from stages.tiles.params import TilesParams
from tests.stages.tiles.tiles_synth import building_corners, buildings, city_context, corner_table, drive_path


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    root = tmp_path_factory.mktemp("loc")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=1)))
    return open_map(root / "maps" / "city")


def test_every_cell_the_drive_crosses_is_in_its_tile_with_both_methods(city):
    m = city.manifest
    cells = city.localizability_in_bbox(-np.inf, -np.inf, np.inf, np.inf)
    assert cells.schema.equals(SCHEMA, check_metadata=False) and cells.schema.field("sigma_2d_m").metadata[b"unit"] \
        == b"m"
    keys = set(zip(cells["cell_i"].to_pylist(), cells["cell_j"].to_pylist()))
    path = drive_path()
    crossed = set(map(tuple, np.floor(path[:-1] / 10.0).astype(int).tolist()))
    assert keys == crossed and m["localizability"]["n_cells"] == len(keys)
    assert cells.num_rows == 2 * len(keys) and sorted(set(cells["method"].to_pylist())) == ["ekf", "mcl"]
    for t in m["tiles"]:
        mine = [k for k in keys if (k[0] // 10, k[1] // 10) == (t["i"], t["j"])]
        assert (LOCALIZABILITY_FILE in t["files"]) == bool(mine)
        if mine:
            assert t["n_localizability_cells"] == 2 * len(mine)
    ekf = cells.filter(pc.equal(cells["method"], "ekf"))
    s = ekf["sigma_2d_m"].to_numpy()
    np.testing.assert_allclose(s, np.sqrt(ekf["cov_ee_m2"].to_numpy() + ekf["cov_nn_m2"].to_numpy()))
    np.testing.assert_allclose(s, np.hypot(ekf["sigma_along_m"].to_numpy(), ekf["sigma_cross_m"].to_numpy()))
    assert m["localizability"]["methods"]["ekf"]["median_sigma_2d_m"] == pytest.approx(np.median(s), abs=1e-4)
    # the city's corners are 0.05 m-class: the EKF is predicted at that class, the MCL on one painted line fails
    assert 0.01 < np.median(s) < 0.2
    weak = m["localizability"]["weak_cells"]
    assert weak and all(w["reason"] for w in weak) and weak == sorted(weak, key=lambda w: -w["sigma_2d_m"])


def test_the_geotiff_export_carries_one_layer_per_method(city, tmp_path):
    import rasterio

    from mapformat.export import export_map

    export_map(city, "geotiff", tmp_path)
    for method in ("ekf", "mcl"):
        with rasterio.open(tmp_path / f"localizability_{method}.vrt") as ds:
            values = ds.read(1)
            assert ds.res == (10.0, 10.0) and np.isfinite(values).sum() == city.manifest["localizability"]["n_cells"]
            assert "predicted sigma_2d" in ds.descriptions[0]
        with rasterio.open(tmp_path / f"localizability_{method}" / "0_0.tif") as ds:
            cells = city.tile_localizability(0, 0).filter(pc.equal(city.tile_localizability(0, 0)["method"], method))
            i, j = cells["cell_i"][0].as_py(), cells["cell_j"][0].as_py()
            row, col = ds.index((i + 0.5) * 10.0, (j + 0.5) * 10.0)
            assert ds.read(1)[row, col] == pytest.approx(cells["sigma_2d_m"][0].as_py(), rel=1e-6)


def test_the_layer_can_be_turned_off_and_such_a_version_reads_as_before(tmp_path):
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(tmp_path, corner_table(xy, dirs, seed=1), params=TilesParams(localizability=False)))
    m = open_map(tmp_path / "maps" / "city")
    assert "localizability" not in m.manifest and m.tile_localizability(0, 0) is None
    assert m.localizability_in_bbox(0, 0, 300, 300).num_rows == 0
    assert all(LOCALIZABILITY_FILE not in t["files"] for t in json.loads(
        (m.path / "manifest.json").read_text())["tiles"])


def test_maps_show_names_the_weak_cells_of_latest(city):
    from mapservice.maps_show import show_lines

    lines = show_lines(city.path.parent)
    head = next(s for s in lines if s.startswith("localizability of v0001"))
    n = city.manifest["localizability"]["n_cells"]
    assert f"({n} cells of 10 m)" in head and "ekf sigma_2d median" in head and "mcl sigma_2d median" in head
    worst = city.manifest["localizability"]["weak_cells"][0]
    assert any(f"at ENU ({worst['east_m']:.1f}, {worst['north_m']:.1f}) m" in s and worst["reason"] in s for s in lines)
