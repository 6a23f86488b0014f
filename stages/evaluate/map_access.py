"""Access to the published map for the evaluation: the map input of the stage, the corners over a drive's extent
and the marking raster as the MCL's likelihood field.

The map is read ONLY through the store (a version path relative to the run's root is that root's: a local
folder, or an ``s3://`` bucket that the loader reads from) and the product's public consumer API
``mapformat.loader.open_map`` (imported lazily, the one documented exception to "stages never import each
other": the loader is what a vehicle links against, and evaluating through it is the point of this stage).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.declare import StageContext
from pipeline.errors import DatasetIOError
from pipeline.storage import join_uri, uri_scheme
from stages.evaluate import mcl
from stages.evaluate.localize_ekf import CornerMap
from stages.evaluate.mcl_params import MarkingLikelihood


def open_published_map(ctx: StageContext):
    from mapformat.loader import open_map  # the public consumer API (see the module doc)

    row = ctx.inputs.read("map").to_pylist()
    if not row:
        raise DatasetIOError("input 'map' (map_tiles) has no published version; hint: run the tiles stage first")
    path = row[-1]["path"]
    if not Path(path).is_absolute() and uri_scheme(path) is None:  # root-relative: on the run's store
        path = join_uri(ctx.settings["root"], path)  # a local path, or the s3:// URI open_map reads from the bucket
    return open_map(path)


def marking_field(mask: np.ndarray, cell_m: float, cfg: MarkingLikelihood) -> np.ndarray:
    """The MCL's likelihood field of a marking window (row 0 south), of the kind ``cfg.field``."""
    if cfg.field == "distance":
        return mcl.distance_likelihood_field(mask, cell_m, cfg.sigma_m)
    return mcl.smooth_marking_mask(mask, cell_m, cfg.blur_m)


# Survey points grow sparse at the edge of a scanner's reach: gaps up to this wide inside the surveyed area are
# closed before the coverage is shrunk by its margin.
COVERAGE_CLOSING_M = 0.5


def observed_area(observed: np.ndarray, cell_m: float, margin_m: float) -> np.ndarray:
    """0/1 cells where the map saw the ground -> bool: gaps up to ``COVERAGE_CLOSING_M`` closed, then shrunk by
    ``margin_m`` (a feature's place is known only to the pose's error, so the edge itself is not trusted)."""
    import cv2

    def disk(radius_m: float) -> np.ndarray:
        r = max(1, int(round(radius_m / cell_m)))
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

    m = (np.asarray(observed) > 0).astype(np.uint8)
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, disk(COVERAGE_CLOSING_M))
    if margin_m > 0:
        m = cv2.erode(m, disk(margin_m), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return m.astype(bool)


def map_inputs(reader, gnss_q: np.ndarray, *, sensor_range_m: float, field: MarkingLikelihood,
               coverage_margin_m: float | None = None):
    """Corner map over the drive's extent (plus ``sensor_range_m`` and 200 m), and a raster fetcher (row 0 south,
    the likelihood field ``field``) when the map has markings. With ``coverage_margin_m`` the windows carry where
    the map saw the ground (``observed_area``); None: the raster is taken as known everywhere."""
    xy = gnss_q[np.all(np.isfinite(gnss_q), axis=1), :2]
    margin = sensor_range_m + 200.0
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    t = reader.corners_in_bbox(lo[0], lo[1], hi[0], hi[1])
    cmap = CornerMap(np.column_stack([t["east_m"].to_numpy(), t["north_m"].to_numpy()]), reader.covariances(t),
                     np.column_stack([t["theta1_rad"].to_numpy(), t["theta2_rad"].to_numpy()]))
    fetch = None
    if reader.cell_m is not None:
        def fetch(e0: float, n0: float, e1: float, n1: float) -> mcl.Raster:
            mask, origin, cell = reader.marking_window(e0, n0, e1, n1)
            observed = None
            if coverage_margin_m is not None:  # read wider by the margin, so the window's own edge is not one
                pad = coverage_margin_m + COVERAGE_CLOSING_M + cell
                wide, wide_origin, _ = reader.observed_window(e0 - pad, n0 - pad, e1 + pad, n1 + pad)
                area = observed_area(np.flipud(wide), cell, coverage_margin_m)
                r0 = int(round((origin[1] - wide_origin[1]) / cell))
                c0 = int(round((origin[0] - wide_origin[0]) / cell))
                observed = area[r0:r0 + mask.shape[0], c0:c0 + mask.shape[1]]
            return mcl.Raster(marking_field(np.flipud(mask), cell, field), origin, cell, observed)
    return cmap, fetch
