"""The real Amsterdam mobile-mapping tile 2293_9698 (EPSG:28992, local coordinates) through the stage."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from pipeline.declare import PartitionKey
from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.markings.compute import compute, plan_tiles
from stages.markings.params import MarkingParams
from stages.markings.raster_io import read_tile_rasters

pytestmark = pytest.mark.realdata


def test_amsterdam_tile_2293_9698(shared_data, tmp_path):
    import laspy

    las = laspy.read(shared_data / "amsterdam_mls_laz" / "2293_9698.laz")
    labelled = laspy.read(shared_data / "amsterdam_mls_laz" / "road_ground_labelled_2293_9698.laz")
    # tile code X_Y: lower-left corner at (X * 50, Y * 50) in RD New; local coordinates from that corner
    x0, y0 = 2293 * 50.0, 9698 * 50.0
    n = len(las.x)
    table = pa.table({"drive": ["ams"] * n, "east_m": np.asarray(las.x) - x0, "north_m": np.asarray(las.y) - y0,
                      "up_m": np.asarray(las.z), "intensity": np.asarray(las.intensity, np.float32)},
                     schema=SCHEMAS["survey_enu"])
    params = MarkingParams()
    plan = plan_tiles(make_context("markings", params, {"survey": table}, settings={"tile_size_m": 50.0}))
    assert PartitionKey(tile_i=0, tile_j=0) in plan
    ctx = make_context("markings", params, {"survey": table}, partition=PartitionKey(tile_i=0, tile_j=0),
                       settings={"tile_size_m": 50.0}, outputs=("raster", "rasters"), workdir=tmp_path)
    row = compute(ctx)["raster"].to_pylist()[0]
    r = read_tile_rasters(ctx.artifact_dirs["rasters"])
    occupied = r.count > 0
    assert row["n_points"] >= 0.99 * n and (r.marking_mask.shape == (500, 500))
    # ground and road only: most occupied cells are smooth enough to be traversable
    assert r.traversable_mask.sum() >= 0.85 * occupied.sum()
    # paint is a small share of the road surface, and there is some (bright parking / lane marks)
    share = r.marking_mask.sum() / r.traversable_mask.sum()
    assert 0.001 < share < 0.05, share
    # heights decode to NAP metres of the file within the 1 mm coding step
    ok = occupied & np.isfinite(r.min_up_m)
    assert np.nanmin(r.min_up_m[ok]) >= float(np.min(las.z)) - 0.001
    assert np.nanmax(r.min_up_m[ok]) <= float(np.max(las.z)) + 0.001
    # cells the upstream labeller called ROAD (1) are mostly traversable
    lab = np.asarray(labelled.label)
    e, nn = np.asarray(labelled.x) - x0, np.asarray(labelled.y) - y0
    road = (lab == 1) & (e < 50) & (nn < 50)
    col, row_px = np.floor(e[road] / 0.1).astype(int), 499 - np.floor(nn[road] / 0.1).astype(int)
    assert r.traversable_mask[row_px, col].mean() >= 0.85
