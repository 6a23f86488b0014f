"""Per-tile vector road markings (``markings.parquet``) from the published marking masks.

Each tile is vectorized on a window reaching ``margin_m`` into its neighbours (a dash or a crosswalk cut by the
tile border keeps its shape), then lines are clipped to the tile and polygons kept by the tile holding their
centroid, so that a feature is stored once and a line's pieces abut at tile borders.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import pyarrow as pa

from stages.common.marking_vectors import MarkingFeature, clip_polyline_to_box, vectorize_markings

MARKINGS_FILE = "markings.parquet"
SCHEMA = pa.schema([
    pa.field("marking_id", pa.int64(), metadata={"meaning": "index within the tile"}),
    pa.field("type", pa.string(), metadata={"values": "lane_solid lane_dashed stop_line crosswalk arrow"}),
    pa.field("geometry", pa.string(), metadata={"values": "LineString Polygon (ring, not repeated first point)"}),
    pa.field("east_m", pa.list_(pa.float64()), metadata={"unit": "m", "frame": "map ENU"}),
    pa.field("north_m", pa.list_(pa.float64()), metadata={"unit": "m", "frame": "map ENU"}),
    pa.field("width_m", pa.float64(), metadata={"unit": "m"}),
    pa.field("length_m", pa.float64(), metadata={"unit": "m", "meaning": "whole feature before clipping"}),
])

# (mask uint8 row 0 = north, origin_east_m, origin_north_m, cell_m) of a tile, or None
MaskOf = Callable[[tuple[int, int]], "tuple[np.ndarray, float, float, float] | None"]


def mosaic_window(e0: float, n0: float, e1: float, n1: float, cell_m: float,
                  parts: list[tuple[np.ndarray, float, float]]) -> np.ndarray:
    """Paste rasters (mask, origin_east_m, origin_north_m; same cell) into the window [e0, e1) x [n0, n1)."""
    c0, s0 = int(round(e0 / cell_m)), int(round(n0 / cell_m))
    c1, s1 = int(round(e1 / cell_m)), int(round(n1 / cell_m))
    out = np.zeros((s1 - s0, c1 - c0), np.uint8)
    for img, oe, on in parts:
        tc0, ts0 = int(round(oe / cell_m)), int(round(on / cell_m))
        h, w = img.shape[:2]
        a_c, b_c, a_s, b_s = max(c0, tc0), min(c1, tc0 + w), max(s0, ts0), min(s1, ts0 + h)
        if a_c < b_c and a_s < b_s:
            out[(s1 - b_s):(s1 - a_s), (a_c - c0):(b_c - c0)] = img[(ts0 + h - b_s):(ts0 + h - a_s),
                                                                    (a_c - tc0):(b_c - tc0)]
    return out


def tile_features(key: tuple[int, int], tile_size_m: float, mask_of: MaskOf,
                  margin_m: float = 10.0) -> list[MarkingFeature]:
    """Features of tile ``key`` (lines clipped to it, polygons whose centroid it holds)."""
    i, j = key
    own = mask_of(key)
    if own is None:
        return []
    cell = own[3]
    parts = []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            got = own if (di, dj) == (0, 0) else mask_of((i + di, j + dj))
            if got is not None and abs(got[3] - cell) < 1e-12:
                parts.append((np.where(got[0] > 0, 255, 0).astype(np.uint8), got[1], got[2]))
    b = (i * tile_size_m, j * tile_size_m, (i + 1) * tile_size_m, (j + 1) * tile_size_m)
    w = (b[0] - margin_m, b[1] - margin_m, b[2] + margin_m, b[3] + margin_m)
    window = mosaic_window(*w, cell, parts)
    out = []
    for f in vectorize_markings(window, w[0], w[1], cell):
        if f.is_polygon:
            c = f.xy_m.mean(axis=0)
            if b[0] <= c[0] < b[2] and b[1] <= c[1] < b[3]:
                out.append(f)
            continue
        for piece in clip_polyline_to_box(f.xy_m, *b):
            if np.linalg.norm(np.diff(piece, axis=0), axis=1).sum() > 1e-6:
                out.append(MarkingFeature(f.type, piece, f.width_m, f.length_m))
    return out


def features_table(features: list[MarkingFeature]) -> pa.Table:
    return pa.table({
        "marking_id": np.arange(len(features), dtype=np.int64),
        "type": [f.type for f in features],
        "geometry": ["Polygon" if f.is_polygon else "LineString" for f in features],
        "east_m": [f.xy_m[:, 0].tolist() for f in features],
        "north_m": [f.xy_m[:, 1].tolist() for f in features],
        "width_m": np.array([f.width_m for f in features], float),
        "length_m": np.array([f.length_m for f in features], float)}, schema=SCHEMA)


def table_features(table: pa.Table) -> list[MarkingFeature]:
    cols = table.to_pydict()
    return [MarkingFeature(t, np.column_stack([e, n]), w, ln) for t, e, n, w, ln in
            zip(cols["type"], cols["east_m"], cols["north_m"], cols["width_m"], cols["length_m"])]


def read_map_features(version_dir, tile_entries: list[dict]) -> list[MarkingFeature]:
    """Every tile's vector markings of a published version (tiles without ``markings.parquet`` have none); each file
    checked against the manifest (sha256, inside the version) and bounded before it is decoded (``loader``)."""
    from pathlib import Path

    from mapformat.loader import decode_table, read_verified
    from pipeline.errors import MapFormatError
    from pipeline.versioned import read_manifest

    files = read_manifest(Path(version_dir))[0].get("files") or {}
    out: list[MarkingFeature] = []
    for entry in tile_entries:
        if MARKINGS_FILE not in (entry.get("files") or {}):
            continue
        rel = f"{entry['dir']}/{MARKINGS_FILE}"
        path = Path(version_dir) / rel
        try:
            out += table_features(decode_table(read_verified(Path(version_dir), rel, files), path))
        except KeyError as exc:
            raise MapFormatError(
                f"{path}: cannot read vector markings ({exc}); hint: run `cornermap tiles verify`"
            ) from exc
    return out
