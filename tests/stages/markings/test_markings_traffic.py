"""Markings under traffic: the lowest consistent surface across scans keeps the paint a standing car hides in
most scans (oracle: the same street without the cars), and the streamed accumulator is order-free."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.markings import TRAFFIC_CARS, traffic_scans, truth_raster
from stages.common.marking_raster.elevation_grid import GridAccumulator
from stages.common.marking_raster.rasterize import halo_px_for, rasterize_grid
from stages.markings.metrics import match_masks
from stages.markings.params import MarkingParams

CELL_M = 0.1
DENSITY = 2500.0  # points per m^2 over all scans: ~5 road points per cell from the 20 % of scans without cars


def _layer(scans, params: MarkingParams):
    halo = halo_px_for(CELL_M, params.threshold_block_m, params.ground_window_m)
    acc = GridAccumulator(-halo * CELL_M, -halo * CELL_M, CELL_M, (200 + 2 * halo, 200 + 2 * halo),
                          surface_band_m=params.surface_band_m)
    for scan in scans:  # one piece per scan, as the stage streams them
        acc.add(scan.points_enu_m, scan.intensity)
    return rasterize_grid(acc.finish(params.min_points_per_cell), halo, **params.rasterize_kwargs()), acc


def _under_cars() -> np.ndarray:
    mask = np.zeros((200, 200), bool)
    for (e0, e1), (n0, n1) in TRAFFIC_CARS:
        mask[int(round(200 - n1 / CELL_M)):int(round(200 - n0 / CELL_M)),
             int(round(e0 / CELL_M)):int(round(e1 / CELL_M))] = True
    return mask


@pytest.mark.parametrize("seed", [0, 1])
def test_cars_on_the_paint_in_80_percent_of_scans_keep_the_recall(seed):
    truth = truth_raster(200, 200, 0.0, 0.0, CELL_M)
    params = MarkingParams()
    clear, _ = _layer(traffic_scans(np.random.default_rng(seed), traffic_share=0.0, density_per_m2=DENSITY), params)
    busy, acc = _layer(traffic_scans(np.random.default_rng(seed), traffic_share=0.8, density_per_m2=DENSITY), params)
    r_clear = match_masks(clear.marking, truth)["recall"]
    scores = match_masks(busy.marking, truth)
    assert r_clear >= 0.97 and scores["recall"] >= r_clear - 0.05 and scores["precision"] >= 0.95, (r_clear, scores)
    under = _under_cars() & truth  # the paint the cars stood on: found as well
    assert busy.marking[under].mean() >= 0.8
    assert busy.traversable[_under_cars()].mean() >= 0.9 and acc.n_above_surface > 0
    # without the lowest surface (every point counts) the cars' cells are not road and their paint is lost
    old, _ = _layer(
        traffic_scans(np.random.default_rng(seed), traffic_share=0.8, density_per_m2=DENSITY),
        MarkingParams(surface_band_m=0),
    )
    assert old.traversable[_under_cars()].mean() < 0.2 and old.marking[under].mean() < 0.2


def test_lowest_surface_is_the_same_whatever_the_scan_order():
    car = np.array([[0.05, 0.05, 1.5], [0.05, 0.05, 0.4]])  # a car roof and side over one cell
    road = np.array([[0.05, 0.05, 0.01], [0.05, 0.05, 0.03], [0.15, 0.05, 0.02]])
    grids = []
    for pieces in (
        [(car, [15.0, 15.0]), (road, [40.0, 42.0, 30.0])],
        [(road, [40.0, 42.0, 30.0]), (car, [15.0, 15.0])],
    ):
        acc = GridAccumulator(0.0, 0.0, 0.1, (1, 2), surface_band_m=0.15)
        for pts, inten in pieces:
            acc.add(pts, np.asarray(inten))
        grids.append((acc.finish(), acc.n_above_surface, acc.n_points))
    for grid, dropped, kept in grids:
        assert grid.count.tolist() == [[2, 1]] and dropped == 2 and kept == 3
        assert grid.min_up_m[0, 0] == pytest.approx(0.01) and grid.max_up_m[0, 0] == pytest.approx(0.03)
        assert grid.mean_intensity[0, 0] == pytest.approx(41.0)
    plain = GridAccumulator(0.0, 0.0, 0.1, (1, 2))  # band 0: every point counts (the survey anchors' grid)
    plain.add(np.vstack([car, road]), np.ones(5))
    assert plain.finish().count.tolist() == [[4, 1]]
