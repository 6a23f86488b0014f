"""The tiles stage's localizability layer: its inputs (corners, the marking rasters, the map drives' paths) handed to
the pure prediction (``stages/common/localizability_cells.py``), the cells back as the layer's table."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from stages.common.localizability import Corners, LocalizabilityConfig

if TYPE_CHECKING:  # pragma: no cover
    from stages.tiles.writer import DriveTrajectory, RasterTile


def raster_window(rasters: list["RasterTile"]):
    """``window(e0, n0, e1, n1) -> (mask, (e_sw, n_sw), cell_m)`` over the stage's marking rasters (row 0 north; 0
    where no raster), the loader's ``marking_window`` before the version exists; masks decoded once each."""
    import cv2

    from mapformat import layout

    tiles = []
    for r in rasters:
        name = next((f for f in layout.MARKING_MASK_FILES if f in r.files), None)
        if name is not None:
            tiles.append((r, name))
    cells = {float(r.meta["cell_m"]) for r, _ in tiles}
    if len(cells) != 1:
        return None
    cell = cells.pop()
    cache: dict[tuple[int, int], np.ndarray] = {}

    def window(e0: float, n0: float, e1: float, n1: float):
        c0, c1 = int(np.floor(e0 / cell + 1e-9)), int(np.ceil(e1 / cell - 1e-9))
        s0, s1 = int(np.floor(n0 / cell + 1e-9)), int(np.ceil(n1 / cell - 1e-9))
        out = np.zeros((s1 - s0, c1 - c0), np.uint8)
        for r, name in tiles:
            tc0 = int(round(float(r.meta["origin_east_m"]) / cell))
            ts0 = int(round(float(r.meta["origin_north_m"]) / cell))
            w, h = int(r.meta["width_px"]), int(r.meta["height_px"])
            a_c, b_c, a_s, b_s = max(c0, tc0), min(c1, tc0 + w), max(s0, ts0), min(s1, ts0 + h)
            if a_c >= b_c or a_s >= b_s:
                continue
            if (r.i, r.j) not in cache:
                img = cv2.imread(str(r.files[name]), cv2.IMREAD_GRAYSCALE)
                cache[(r.i, r.j)] = np.zeros((h, w), np.uint8) if img is None else (img > 0).astype(np.uint8)
            img = cache[(r.i, r.j)]
            out[(s1 - b_s):(s1 - a_s), (a_c - c0):(b_c - c0)] = img[(ts0 + h - b_s):(ts0 + h - a_s),
                                                                    (a_c - tc0):(b_c - tc0)]
        return out, (c0 * cell, s0 * cell), cell

    return window


def localizability_table(corners: pa.Table, trajectories: list["DriveTrajectory"], rasters: list["RasterTile"],
                         correlation: tuple[float, float] | None, cfg: LocalizabilityConfig) -> pa.Table:
    """The layer's cells (mapformat/localizability.py's columns) of this version's corners, rasters and drives.
    The corners' covariance is read through the loader's public API (``MapReader.covariances``)."""
    from dataclasses import replace

    from mapformat.loader import MapReader
    from mapformat.localizability import cells_table
    from stages.common.localizability_cells import predict_cells

    cols = lambda *names: np.column_stack([corners[n].to_numpy() for n in names]) if corners.num_rows \
        else np.zeros((0, len(names)))
    layer = Corners(cols("east_m", "north_m"), MapReader.covariances(corners) if corners.num_rows
                    else np.zeros((0, 2, 2)), cols("theta1_rad", "theta2_rad"),
                    corners["convex"].to_numpy(zero_copy_only=False).astype(bool) if corners.num_rows
                    else np.zeros(0, bool))
    if correlation is not None:
        cfg = replace(cfg, corr_share=float(correlation[0]), corr_length_m=float(correlation[1]))
    paths = [t.pose_xyz_qxyzw[:, :2] for t in trajectories]
    return cells_table(predict_cells(paths, layer, raster_window(rasters), cfg))
