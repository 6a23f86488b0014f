"""The localizability layer of a version: ``tiles/{i}_{j}/localizability.parquet``, one row per cell of the driven
roads and per localizer, the predicted position uncertainty there (computed by the tiles stage with
``stages/common/localizability_cells.predict_cells``; docs/map-format.md, "localizability.parquet").

This module states the file's columns (units in the Arrow field metadata, stored in the file), cuts the cells into
tiles, summarises them for the manifest and rasterises them for the GeoTIFF export.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

LOCALIZABILITY_FILE = "localizability.parquet"
MAX_WEAK_LISTED = 50  # weak cells named in the manifest's summary (worst first)


def _f(name: str, typ: pa.DataType, unit: str = "", doc: str = "") -> pa.Field:
    meta = {k: v for k, v in (("unit", unit), ("doc", doc)) if v}
    return pa.field(name, typ, nullable=False, metadata=meta or None)


SCHEMA = pa.schema([
    _f("cell_i", pa.int32(), doc="cell key: floor(east_m / cell_m)"),
    _f("cell_j", pa.int32(), doc="cell key: floor(north_m / cell_m)"),
    _f("method", pa.string(), doc="ekf (corner EKF with road markings) | mcl (marking MCL)"),
    _f("east_m", pa.float64(), "m", "map ENU: the road point the prediction is for (a driven sample in the cell)"),
    _f("north_m", pa.float64(), "m", "map ENU"),
    _f("heading_rad", pa.float64(), "rad", "the road's axis in the cell, ENU counter-clockwise from east"),
    _f("sigma_along_m", pa.float64(), "m", "predicted std of the position error along the road"),
    _f("sigma_cross_m", pa.float64(), "m", "... across the road"),
    _f("sigma_2d_m", pa.float64(), "m", "sqrt(cov_ee + cov_nn): the predicted RMS of the 2-D position error"),
    _f("sigma_heading_deg", pa.float64(), "deg", "predicted std of the heading error"),
    _f("cov_ee_m2", pa.float64(), "m^2", "predicted 2x2 position covariance, map ENU"),
    _f("cov_en_m2", pa.float64(), "m^2"),
    _f("cov_nn_m2", pa.float64(), "m^2"),
    _f("n_corners_visible", pa.int32(), doc="map corners in view (median over the cell's samples)"),
    _f("n_wall_axes", pa.int32(), doc="distinct wall axes (mod 180 deg, 15 deg bins) of the corners in view"),
    _f("n_marking_px", pa.int32(), doc="painted raster cells within the feature range"),
    _f("n_samples", pa.int32(), doc="road samples of the map drives the cell's prediction averages"),
    _f("status", pa.string(), doc="ok | weak | fail"),
    _f("reason", pa.string(), doc="why weak or fail ('' when ok)"),
])


def cells_table(columns: dict[str, list]) -> pa.Table:
    """The layer's columns (``predict_cells``'s dict) as a table of ``SCHEMA``, sorted by cell then method."""
    table = pa.table({f.name: pa.array(columns[f.name], f.type) for f in SCHEMA}, schema=SCHEMA)
    return table.sort_by([("cell_i", "ascending"), ("cell_j", "ascending"), ("method", "ascending")])


def split_by_tile(table: pa.Table, cell_m: float, tile_size_m: float) -> dict[tuple[int, int], pa.Table]:
    """Tile key -> its cells (a cell belongs to the tile holding its south-west corner; cell_m divides the tile)."""
    if table.num_rows == 0:
        return {}
    per = int(round(tile_size_m / cell_m))
    ti = np.floor_divide(table["cell_i"].to_numpy(), per)
    tj = np.floor_divide(table["cell_j"].to_numpy(), per)
    out = {}
    for key in sorted(set(zip(ti.tolist(), tj.tolist()))):
        out[key] = table.filter(pa.array((ti == key[0]) & (tj == key[1])))
    return out


def summary(table: pa.Table, cell_m: float) -> dict[str, Any]:
    """The manifest's ``localizability`` entry: per method the median and p95 sigma_2d and the weak cells' count;
    the weak and failing cells (worst first, at most MAX_WEAK_LISTED) with their reason."""
    methods: dict[str, Any] = {}
    weak = []
    for method in sorted(set(table["method"].to_pylist())):
        t = table.filter(pc.equal(table["method"], method))
        s = t["sigma_2d_m"].to_numpy()
        status = np.asarray(t["status"].to_pylist())
        methods[method] = {"median_sigma_2d_m": round(float(np.median(s)), 4) if len(s) else None,
                           "p95_sigma_2d_m": round(float(np.percentile(s, 95)), 4) if len(s) else None,
                           "n_weak": int((status != "ok").sum())}
        for k in np.flatnonzero(status != "ok"):
            weak.append({"method": method, "east_m": round(float(t["east_m"][k].as_py()), 2),
                         "north_m": round(float(t["north_m"][k].as_py()), 2),
                         "sigma_2d_m": round(float(s[k]), 4), "status": str(status[k]),
                         "reason": t["reason"][k].as_py()})
    weak.sort(key=lambda w: (-w["sigma_2d_m"], w["method"], w["east_m"], w["north_m"]))
    n_cells = len(set(zip(table["cell_i"].to_pylist(), table["cell_j"].to_pylist())))
    return {"file": LOCALIZABILITY_FILE, "cell_m": float(cell_m), "n_cells": n_cells, "methods": methods,
            "weak_cells": weak[:MAX_WEAK_LISTED]}


def rasterize(table: pa.Table, method: str, tile_bounds_m: tuple[float, float, float, float], cell_m: float
              ) -> np.ndarray:
    """A tile's cells of one method as a float32 raster of sigma_2d_m (row 0 = north, NaN = no cell)."""
    e0, n0, e1, n1 = tile_bounds_m
    w, h = int(round((e1 - e0) / cell_m)), int(round((n1 - n0) / cell_m))
    out = np.full((h, w), np.nan, np.float32)
    t = table.filter(pc.equal(table["method"], method))
    col = t["cell_i"].to_numpy() - int(round(e0 / cell_m))
    row = h - 1 - (t["cell_j"].to_numpy() - int(round(n0 / cell_m)))
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out[row[ok], col[ok]] = t["sigma_2d_m"].to_numpy()[ok]
    return out
