"""Loader API: bbox / radius queries against brute force, half-open tile borders, marking windows, LRU."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from mapformat.loader import open_map
from pipeline.errors import UnknownNameError
from stages.tiles.compute import compute
from stages.tiles.params import TilesParams
from tests.stages.tiles.tiles_synth import (
    CELL_M,
    LINE_EAST_M,
    TILE_M,
    UNSURVEYED_EAST_M,
    building_corners,
    buildings,
    city_context,
    corner_table,
)


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    root = tmp_path_factory.mktemp("loader")
    xy, dirs, _ = building_corners(buildings())
    extra_xy = np.array([[100.0, 37.0], [99.999999, 37.0], [0.0, 0.0]])  # on and next to tile borders
    xy = np.vstack([xy, extra_xy])
    dirs = np.vstack([dirs, np.zeros((3, 2))])
    corners = corner_table(xy, dirs, seed=2, noise_m=0.0)
    compute(city_context(root, corners))
    return root / "maps" / "city", corners


def _brute(corners: pa.Table, mask: np.ndarray) -> set[int]:
    return set(corners["corner_id"].to_numpy()[mask].tolist())


def test_bbox_and_radius_queries_match_brute_force(published):
    map_dir, corners = published
    reader = open_map(map_dir)
    e, n = corners["east_m"].to_numpy(), corners["north_m"].to_numpy()
    rng = np.random.default_rng(7)
    for _ in range(25):
        e0, n0 = rng.uniform(-20, 280, 2)
        e1, n1 = e0 + rng.uniform(1, 150), n0 + rng.uniform(1, 150)
        got = reader.corners_in_bbox(e0, n0, e1, n1)
        assert set(got["corner_id"].to_pylist()) == _brute(corners, (e >= e0) & (e < e1) & (n >= n0) & (n < n1))
        ce, cn, r = rng.uniform(0, 300), rng.uniform(0, 300), rng.uniform(5, 120)
        got = reader.corners_within(ce, cn, r)
        assert set(got["corner_id"].to_pylist()) == _brute(corners, (e - ce) ** 2 + (n - cn) ** 2 <= r * r)
    assert reader.corners_in_bbox(1000, 1000, 1100, 1100).num_rows == 0
    assert reader.corners_in_bbox(0, 0, 300, 300).schema.names == corners.schema.names


def test_tile_borders_are_half_open(published):
    map_dir, corners = published
    reader = open_map(map_dir)
    ids = corners["corner_id"].to_numpy()
    on_border, just_west, at_origin = ids[-3], ids[-2], ids[-1]
    assert on_border in reader.tile_corners(1, 0)["corner_id"].to_pylist()
    assert just_west in reader.tile_corners(0, 0)["corner_id"].to_pylist()
    assert at_origin in reader.tile_corners(0, 0)["corner_id"].to_pylist()
    assert on_border not in reader.corners_in_bbox(0, 0, 100, 100)["corner_id"].to_pylist()


def test_covariances_are_2x2_psd(published):
    reader = open_map(published[0])
    cov = reader.covariances(reader.corners_within(50, 50, 60))
    assert cov.shape[1:] == (2, 2) and np.allclose(cov, np.swapaxes(cov, 1, 2))
    assert (np.linalg.eigvalsh(cov) > 0).all()


def test_marking_window_places_the_painted_line(published):
    reader = open_map(published[0])
    assert reader.cell_m == CELL_M
    mask, (oe, on), cell = reader.marking_window(40.0, 90.0, 60.0, 130.0)  # spans tiles (0,0) and (0,1)
    assert (oe, on, cell) == (40.0, 90.0, CELL_M) and mask.shape == (80, 40) and mask.dtype == np.uint8
    cols = np.flatnonzero(mask.any(axis=0))
    assert cols.tolist() == [int((LINE_EAST_M - oe) // cell)]
    assert (mask[:, cols[0]] == 255).all()  # continuous across the tile border
    mask2, _, _ = reader.marking_window(150.0, 0.0, 170.0, 10.0)  # a tile without rasters
    assert mask2.shape == (20, 40) and not mask2.any()
    tile = reader.tile_marking(0, 2)
    assert tile.shape == (200, 200) and reader.tile_marking(2, 2) is None


def test_observed_window_is_where_the_tiles_saw_ground(published):
    """The coverage mosaic on the marking lattice: 1 where a tile's point_count is positive, 0 in tile (0, 2)'s
    unsurveyed east strip and outside every raster; the mosaic of one tile equals its own layer."""
    reader = open_map(published[0])
    e0, n0, e1, n1 = 60.0, 150.0, 100.0, 250.0  # tiles (0, 1) and (0, 2), across the strip's edge, and beyond j = 2
    obs, origin, cell = reader.observed_window(e0, n0, e1, n1)
    mask, origin_m, _ = reader.marking_window(e0, n0, e1, n1)
    assert obs.shape == mask.shape and origin == origin_m and cell == CELL_M and obs.dtype == np.uint8
    north = origin[1] + (obs.shape[0] - np.arange(obs.shape[0]) - 0.5) * cell  # row 0 = north edge
    east = origin[0] + (np.arange(obs.shape[1]) + 0.5) * cell
    expected = (north[:, None] < 3 * TILE_M) & ((north[:, None] < 2 * TILE_M) | (east[None] < UNSURVEYED_EAST_M))
    np.testing.assert_array_equal(obs.astype(bool), expected)
    tile, _, _ = reader.observed_window(0.0, 2 * TILE_M, TILE_M, 3 * TILE_M)
    np.testing.assert_array_equal(tile, (reader.tile_layer(0, 2, "point_count") > 0).astype(np.uint8))


def test_lazy_lru_and_pinned_version(published):
    map_dir, _ = published
    reader = open_map(map_dir, "v0001", cache_tiles=2)
    assert len(reader._corners._items) == 0  # nothing read at open
    reader.corners_within(50, 50, 10)
    reader.corners_in_bbox(0, 0, 300, 300)
    assert len(reader._corners._items) == 2  # bounded by the cache size
    with pytest.raises(UnknownNameError, match="no version v0007"):
        open_map(map_dir, "v7")
    with pytest.raises(UnknownNameError, match="no such map"):
        open_map(map_dir.parent / "nope")


def test_reader_pinned_while_a_new_version_is_published(published, tmp_path):
    import shutil

    src, corners = published
    shutil.copytree(src.parent.parent, tmp_path / "root")  # do not change the shared fixture
    map_dir = tmp_path / "root" / "maps" / "city"
    reader = open_map(map_dir)
    before = reader.corners_in_bbox(0, 0, 300, 300).num_rows
    compute(city_context(tmp_path / "root", corners.slice(0, 100), fingerprint="other",
                         params=TilesParams(min_corners_per_km=0, max_empty_path_tile_share=1.0)))
    reader.clear_cache()
    assert reader.corners_in_bbox(0, 0, 300, 300).num_rows == before
    assert open_map(map_dir).all_corners().num_rows == 100


def test_the_map_states_the_pose_graphs_error_correlation(tmp_path):
    """The pose graph's kernel (metadata of its poses) is published in the manifest and read back by the loader;
    a map without it states none; a malformed entry is a named format error."""
    from mapformat.loader import _error_correlation
    from pipeline.errors import MapFormatError

    xy, dirs, _ = building_corners(buildings())
    corners = corner_table(xy, dirs, seed=2, noise_m=0.0)
    compute(city_context(tmp_path / "a", corners, poses_metadata={
        "pose_error_correlation": {"share": 0.73, "length_m": 47.7, "n_pairs": 240}}))
    assert open_map(tmp_path / "a" / "maps" / "city").corner_error_correlation == (0.73, 47.7)
    compute(city_context(tmp_path / "b", corners))
    assert open_map(tmp_path / "b" / "maps" / "city").corner_error_correlation is None
    for bad in ({"share": 1.2, "length_m": 40.0}, {"share": 0.5}, {"share": "x", "length_m": 3.0},
                {"share": 0.5, "length_m": -1.0}):
        with pytest.raises(MapFormatError, match="corner_error_correlation"):
            _error_correlation(bad, tmp_path / "manifest.json")


def test_the_map_states_its_frame_error(tmp_path):
    """The pose graph's map frame error (metadata of its poses) is published in the manifest and read back; a map
    published before it states none (its corner covariances held the frame's error); a malformed entry is a named
    format error."""
    from mapformat.loader import _map_frame
    from pipeline.errors import MapFormatError

    xy, dirs, _ = building_corners(buildings())
    corners = corner_table(xy, dirs, seed=2, noise_m=0.0)
    cov = [[0.09, 0.001, 0.0], [0.001, 0.1, 0.0], [0.0, 0.0, 4e-6]]
    compute(city_context(tmp_path / "a", corners, poses_metadata={
        "map_frame": {"reference_en_m": [120.0, 80.0], "cov_shift_rotation": cov, "source": "GNSS/INS"}}))
    frame = open_map(tmp_path / "a" / "maps" / "city").map_frame
    np.testing.assert_allclose(frame["cov_shift_rotation"], cov)
    np.testing.assert_allclose(frame["reference_en_m"], [120.0, 80.0])
    assert frame["source"] == "GNSS/INS"
    compute(city_context(tmp_path / "b", corners))
    assert open_map(tmp_path / "b" / "maps" / "city").map_frame is None
    for bad in ({"reference_en_m": [1.0, 2.0]}, {"reference_en_m": [1.0], "cov_shift_rotation": cov},
                {"reference_en_m": [1.0, 2.0], "cov_shift_rotation": [[1.0, 2.0], [2.0, 1.0]]},
                {"reference_en_m": [1.0, 2.0], "cov_shift_rotation": [[1, 0, 0], [0, -1, 0], [0, 0, 1]]},
                {"reference_en_m": [1.0, "x"], "cov_shift_rotation": cov}):
        with pytest.raises(MapFormatError, match="map_frame"):
            _map_frame(bad, tmp_path / "manifest.json")
