"""Per-tile PNG + JSON sidecar: round trip, read without this package's reader, malformed files."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pipeline.errors import DatasetIOError, FormatError, MapFormatError
from stages.markings.raster_io import SIDECAR, TileRasters, read_tile_rasters, write_tile_rasters


def _rasters(seed: int = 0) -> TileRasters:
    rng = np.random.default_rng(seed)
    shape = (40, 30)
    count = rng.integers(0, 5, shape)
    empty = count == 0
    up = np.where(empty, np.nan, 12.0 + rng.uniform(-3, 3, shape))
    return TileRasters(marking_mask=rng.random(shape) < 0.1, traversable_mask=rng.random(shape) < 0.7,
                       intensity=np.where(empty, np.nan, rng.uniform(0, 40000, shape)), min_up_m=up,
                       mean_up_m=up + 0.01, count=count, origin_east_m=-300.0, origin_north_m=200.0, cell_m=0.1,
                       meta={"tile_i": -3, "tile_j": 2, "source": "survey"})


def test_round_trip_is_lossless_up_to_the_stated_scale(tmp_path):
    r = _rasters()
    write_tile_rasters(tmp_path, r)
    back = read_tile_rasters(tmp_path)
    np.testing.assert_array_equal(back.marking_mask, r.marking_mask)
    np.testing.assert_array_equal(back.traversable_mask, r.traversable_mask)
    np.testing.assert_array_equal(back.count, r.count)
    sidecar = json.loads((tmp_path / SIDECAR).read_text())
    for got, want, layer in ((back.min_up_m, r.min_up_m, "elevation_min"), (back.intensity, r.intensity, "intensity")):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        ok = ~np.isnan(want)
        assert np.abs(got[ok] - want[ok]).max() <= sidecar["layers"][layer]["scale"] / 2 + 1e-12
    assert sidecar["layers"]["elevation_min"]["scale"] == pytest.approx(0.001)  # mm for a 6 m range
    assert (back.origin_east_m, back.origin_north_m, back.cell_m) == (-300.0, 200.0, 0.1)
    assert back.meta["tile_i"] == -3 and back.meta["source"] == "survey"
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary files left behind


def test_files_decode_with_plain_opencv_and_the_sidecar(tmp_path):
    """What a C++/Rust localizer does: read the PNG and apply scale/offset from the JSON."""
    r = _rasters(1)
    write_tile_rasters(tmp_path, r)
    sidecar = json.loads((tmp_path / SIDECAR).read_text())
    lay = sidecar["layers"]["elevation_mean"]
    pixels = cv2.imread(str(tmp_path / lay["file"]), cv2.IMREAD_UNCHANGED)
    assert pixels.dtype == np.uint16 and pixels.shape == (sidecar["height_px"], sidecar["width_px"])
    ok = pixels != lay["nodata"]
    decoded = lay["offset"] + (pixels[ok].astype(float) - 1) * lay["scale"]
    np.testing.assert_allclose(decoded, r.mean_up_m[ok], atol=lay["scale"])
    mask = cv2.imread(str(tmp_path / "marking_mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    assert sidecar["row_order"].startswith("row 0 = north") and sidecar["origin_corner"] == "south_west"


def test_missing_sidecar_or_png_is_a_dataset_io_error(tmp_path):
    with pytest.raises(DatasetIOError, match="raster.json"):
        read_tile_rasters(tmp_path)
    write_tile_rasters(tmp_path, _rasters())
    (tmp_path / "intensity.png").unlink()
    with pytest.raises(DatasetIOError, match="intensity.png"):
        read_tile_rasters(tmp_path)


def test_malformed_sidecar_and_pngs_are_format_errors(tmp_path):
    write_tile_rasters(tmp_path, _rasters())
    path = tmp_path / SIDECAR
    good = json.loads(path.read_text())
    path.write_text("{not json")
    with pytest.raises(FormatError, match="not valid JSON"):
        read_tile_rasters(tmp_path)
    path.write_text(json.dumps({**good, "format_version": 99}))
    with pytest.raises(MapFormatError, match="format_version 99"):
        read_tile_rasters(tmp_path)
    path.write_text(json.dumps({k: v for k, v in good.items() if k != "cell_m"}))
    with pytest.raises(FormatError, match="cell_m"):
        read_tile_rasters(tmp_path)
    path.write_text(json.dumps(good))
    cv2.imwrite(str(tmp_path / "marking_mask.png"), np.zeros((5, 5), np.uint16))
    with pytest.raises(FormatError, match="expected uint8"):
        read_tile_rasters(tmp_path)
    (tmp_path / "traversable_mask.png").write_bytes(b"garbage")
    cv2.imwrite(str(tmp_path / "marking_mask.png"), np.zeros((40, 30), np.uint8))
    with pytest.raises(FormatError, match="not a readable PNG"):
        read_tile_rasters(tmp_path)
