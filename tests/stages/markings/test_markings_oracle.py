"""Oracles of the pure algorithms: a painted street with known truth, hand-made grids, an independent
reference for the per-cell statistics and the tolerant pixel metrics."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from fixtures.markings import CAR, ROAD_NORTH_M, make_street, truth_raster
from stages.common.marking_raster.elevation_grid import GridAccumulator, grid_points
from stages.common.marking_raster.rasterize import halo_px_for, rasterize_grid
from stages.common.marking_raster.threshold import extract_markings, metres_to_odd_px
from stages.common.marking_raster.traversable import find_traversable, neighbour_step_m, open_ground_m
from stages.markings.metrics import match_masks
from stages.markings.params import MarkingParams

CELL_M = 0.1


def _street_layer(seed: int, params: MarkingParams = MarkingParams()):
    street = make_street(np.random.default_rng(seed))
    halo = halo_px_for(CELL_M, params.threshold_block_m, params.ground_window_m)
    grid = grid_points(street.points_enu_m, street.intensity, -halo * CELL_M, -halo * CELL_M, CELL_M,
                       (200 + 2 * halo, 200 + 2 * halo))
    return rasterize_grid(grid, halo, **params.rasterize_kwargs())


@pytest.mark.parametrize("seed", [0, 1])
def test_painted_street_gives_the_expected_pixels(seed):
    layer = _street_layer(seed)
    truth = truth_raster(200, 200, 0.0, 0.0, CELL_M)
    scores = match_masks(layer.marking, truth, tolerance_px=1)
    assert scores["precision"] >= 0.97 and scores["recall"] >= 0.97, scores
    # exact-pixel agreement is high too (edges of the 0.15 m line straddle two cells)
    exact = match_masks(layer.marking, truth, tolerance_px=0)
    assert exact["precision"] >= 0.85 and exact["recall"] >= 0.85, exact


def test_curb_and_parked_car_are_not_traversable():
    layer = _street_layer(0)
    trav = layer.traversable
    north_of_row = (199 - np.arange(200) + 0.5) * CELL_M  # pixel-centre north per row
    for curb_north in ROAD_NORTH_M:  # the cells on both sides of each curb edge
        rows = np.nonzero(np.abs(north_of_row - curb_north) < CELL_M)[0]
        assert len(rows) == 2 and not trav[rows, :].any()
    (ce0, ce1), (cn0, cn1) = CAR
    car_rows = slice(int(round(200 - cn1 / CELL_M)), int(round(200 - cn0 / CELL_M)))
    car_cols = slice(int(round(ce0 / CELL_M)), int(round(ce1 / CELL_M)))
    assert not trav[car_rows, car_cols].any()
    # open sloped road away from the curbs and the car stays traversable
    road = np.zeros_like(trav)
    road[int(200 - 13.5 / CELL_M):int(200 - 7.0 / CELL_M), :] = True
    assert trav[road].mean() >= 0.98


def test_no_paint_no_markings():
    """Asphalt with texture but no paint: the adaptive offset keeps false positives near zero."""
    rng = np.random.default_rng(3)
    image = np.clip(rng.normal(80, 6, (300, 300)) + np.linspace(0, 60, 300)[None, :], 0, 255).astype(np.uint8)
    trav = np.ones(image.shape, bool)
    mask, offset = extract_markings(image, trav, block_px=25, offset_sigma=3.0, min_offset_levels=6,
                                    min_area_px=5)
    assert mask.mean() < 1e-3 and offset >= 6


def test_paint_found_despite_intensity_drift_that_defeats_a_global_threshold():
    rng = np.random.default_rng(4)
    ramp = np.linspace(40, 160, 300)[None, :].repeat(300, axis=0)
    truth = np.zeros((300, 300), bool)
    truth[100:102, 10:290] = True  # a two-cell line across the whole drift
    image = np.clip(ramp + 45 * truth + rng.normal(0, 3, ramp.shape), 0, 255).astype(np.uint8)
    mask, _ = extract_markings(image, np.ones_like(truth), block_px=25, offset_sigma=3.0, min_offset_levels=6,
                               min_area_px=5)
    scores = match_masks(mask, truth)
    assert scores["precision"] > 0.95 and scores["recall"] > 0.95
    global_mask = image > np.percentile(image, 99)
    assert match_masks(global_mask, truth)["recall"] < 0.6  # a global threshold misses the dark end


def test_bright_sidewalk_across_a_curb_is_not_paint():
    image = np.full((100, 100), 60, np.uint8)
    image[:, 52:] = 140  # bright sidewalk
    trav = np.ones((100, 100), bool)
    trav[:, 50:52] = False  # the curb
    mask, _ = extract_markings(image, trav, block_px=25, offset_sigma=3.0, min_offset_levels=6)
    assert not mask.any()


def test_elevation_grid_matches_a_per_point_reference():
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-0.3, 1.3, 400), rng.uniform(-0.3, 1.3, 400), rng.normal(0, 1, 400)])
    inten = rng.uniform(0, 100, 400)
    acc = GridAccumulator(0.0, 0.0, 0.25, (4, 4))
    acc.add(pts[:150], inten[:150])  # streamed in two pieces
    acc.add(pts[150:], inten[150:])
    grid = acc.finish()
    cells: dict[tuple[int, int], list[int]] = {}
    for k, (e, n, _) in enumerate(pts):
        col, row_from_south = int(np.floor(e / 0.25)), int(np.floor(n / 0.25))
        if 0 <= col < 4 and 0 <= row_from_south < 4:
            cells.setdefault((3 - row_from_south, col), []).append(k)
    assert grid.count.sum() == sum(len(v) for v in cells.values()) == acc.n_points
    for (row, col), idx in cells.items():
        assert grid.count[row, col] == len(idx)
        assert grid.min_up_m[row, col] == pts[idx, 2].min()
        assert grid.max_up_m[row, col] == pts[idx, 2].max()
        assert grid.mean_up_m[row, col] == pytest.approx(pts[idx, 2].mean())
        assert grid.mean_intensity[row, col] == pytest.approx(inten[idx].mean())
    empty = grid.count == 0
    assert np.isnan(grid.min_up_m[empty]).all()


def test_grid_drops_nonfinite_points_and_honours_min_points():
    pts = np.array([[0.05, 0.05, 1.0], [0.05, 0.05, np.nan], [0.15, 0.05, 2.0], [0.15, 0.05, 3.0]])
    grid = grid_points(pts, np.ones(4), 0.0, 0.0, 0.1, (1, 2), min_points=2)
    assert grid.count.tolist() == [[1, 2]]
    assert np.isnan(grid.min_up_m[0, 0]) and grid.min_up_m[0, 1] == 2.0


def test_neighbour_step_and_ground_opening():
    h = np.zeros((9, 9))
    h[4, 4] = 0.2
    h[0, 0] = np.nan
    step = neighbour_step_m(h)
    assert step[4, 4] == pytest.approx(0.2) and step[3, 3] == pytest.approx(0.2) and step[1, 1] == 0
    assert np.isnan(step[0, 0])
    yy, xx = np.mgrid[0:120, 0:120]
    plane = 0.01 * xx - 0.004 * yy
    box = plane.copy()
    box[40:55, 45:65] += 1.5
    ground = open_ground_m(box, 21)
    far = np.ones_like(box, bool)
    far[40 - 21:55 + 21, 45 - 21:65 + 21] = False
    far[:21], far[-21:], far[:, :21], far[:, -21:] = False, False, False, False  # border: edge replication
    np.testing.assert_allclose(ground[far], plane[far], atol=1e-12)  # a plane is kept exactly
    # near the box the opening may sit up to slope x window above the plane; the box itself is dropped
    assert np.abs(ground - plane)[21:-21, 21:-21].max() <= (0.01 + 0.004) * 21
    assert (box - ground)[40:55, 45:65].min() > 1.2


def test_spread_excludes_a_wall_cell():
    h_min = np.zeros((5, 5))
    h_max = np.zeros((5, 5))
    h_max[2, 2] = 3.0
    trav = find_traversable(h_min, h_max, np.ones((5, 5)), max_step_m=0.05, max_spread_m=0.15,
                            ground_window_px=3, max_above_ground_m=0.3)
    assert not trav[2, 2] and trav.sum() == 24


def test_metrics_agree_with_a_distance_transform():
    rng = np.random.default_rng(6)
    pred, truth = rng.random((80, 80)) < 0.05, rng.random((80, 80)) < 0.05
    scores = match_masks(pred, truth, tolerance_px=1)
    # independent: Chebyshev distance to the nearest truth / predicted pixel
    d_truth = ndimage.distance_transform_cdt(~truth, metric="chessboard")
    d_pred = ndimage.distance_transform_cdt(~pred, metric="chessboard")
    assert scores["precision"] == pytest.approx((d_truth[pred] <= 1).mean())
    assert scores["recall"] == pytest.approx((d_pred[truth] <= 1).mean())
    with pytest.raises(ValueError):
        match_masks(pred, truth[:10])


def test_block_size_is_odd_and_in_metres():
    assert metres_to_odd_px(2.5, 0.1) == 25 and metres_to_odd_px(2.0, 0.1) == 21 and metres_to_odd_px(0.1, 0.1) == 3
    with pytest.raises(ValueError):
        extract_markings(np.zeros((5, 5), np.uint8), np.ones((5, 5), bool), block_px=4, offset_sigma=1,
                         min_offset_levels=1)


def test_params_reject_unknown_keys_and_bad_combinations():
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        MarkingParams(cel_m=0.1)
    with pytest.raises(ValidationError):
        MarkingParams(threshold_block_m=0.2)
    with pytest.raises(ValidationError):
        MarkingParams(intensity_low_pct=50, intensity_high_pct=40)
