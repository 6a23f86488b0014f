"""Oracle tests of the marking raster's coverage (``raster_coverage``): beyond the area the map saw, its 0 means "not
known", and a road feature placed there must not pull the pose towards the mapped part of a crosswalk the survey
cut."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.evaluate import ground_ring_scan, paint_markings
from stages.common.road_features import extract_road_features
from stages.evaluate import mcl
from stages.evaluate.map_access import COVERAGE_CLOSING_M, map_inputs, observed_area

CELL = 0.1
T_VEHICLE_LIDAR = np.eye(4)
T_VEHICLE_LIDAR[2, 3] = 1.8
SURVEY_EDGE_M = 60.0  # the survey saw the ground west of this: it cuts the crosswalk at x = 58-62 in half


def _cut_world():
    truth, origin = paint_markings(200.0, 40.0, CELL, road_y_m=20.0, crosswalks_x_m=(60.0, 130.0))
    edge = int(round(SURVEY_EDGE_M / CELL))
    mapped = truth.copy()
    mapped[:, edge:] = 0
    seen = np.zeros(truth.shape, np.uint8)
    seen[:, :edge] = 1
    return truth, mapped, seen, origin


@pytest.mark.parametrize("seed,x0", [(0, 52.0), (1, 55.0), (2, 57.0)])
def test_features_beyond_the_survey_edge_no_longer_pull_the_scan_likelihood(seed, x0):
    """A scan from the true pose, its paint the whole world's; the map holds the paint west of the survey edge.
    Along the road the likelihood's maximum sits 0.4-1.5 m behind the truth when every feature counts (the
    crosswalk's eastern half slides onto its mapped western half), and at the truth once the features that fall
    beyond the surveyed area are dropped."""
    truth, mapped, seen, origin = _cut_world()
    q = np.array([x0, 18.0, 0.0])
    xyz, inten, ring = ground_ring_scan(q, truth, origin, CELL, np.random.default_rng(seed))
    feats = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR, voxel_m=0.1)
    field = mcl.distance_likelihood_field(mapped, CELL, 0.2)
    plain = mcl.Raster(field, origin, CELL)
    covered = mcl.Raster(field, origin, CELL, observed_area(seen, CELL, 1.0))
    keep = mcl.observed_features(feats, q, covered)
    assert 0.2 < keep.mean() < 0.8
    dx = np.arange(-1.5, 1.51, 0.05)
    poses = np.column_stack([q[0] + dx, np.full_like(dx, q[1]), np.zeros_like(dx)])
    biased = dx[np.argmax(mcl.correlation_scores(poses, feats, plain))]
    fixed = dx[np.argmax(mcl.correlation_scores(poses, feats[keep], covered))]
    assert biased <= -0.3, biased
    assert abs(fixed) <= 0.1, fixed


def test_observed_features_place_by_the_pose_and_drop_what_leaves_the_window():
    values = np.zeros((100, 100), np.float32)
    seen = np.zeros((100, 100), bool)
    seen[:, :50] = True  # the western half of a 10 m window whose lower-left corner is (100, 200)
    raster = mcl.Raster(values, (100.0, 200.0), CELL, seen)
    feats = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 30.0]])  # ahead, behind, far left (out of the window)
    east = mcl.observed_features(feats, np.array([105.0, 205.0, 0.0]), raster)
    west = mcl.observed_features(feats, np.array([105.0, 205.0, np.pi]), raster)  # turned: ahead is west
    assert east.tolist() == [False, True, False] and west.tolist() == [True, False, False]
    assert mcl.observed_features(feats, np.zeros(3), mcl.Raster(values, (100.0, 200.0), CELL)).all()


def test_observed_area_closes_sparse_gaps_and_shrinks_by_the_margin():
    seen = np.zeros((200, 200), np.uint8)
    seen[50:150, 50:150] = 1
    seen[100, 100] = seen[101, 101] = 0  # sparse survey points: gaps a few cells wide
    seen[80:83, 120] = 0
    for margin_m in (0.0, 0.5, 1.0):
        area = observed_area(seen, CELL, margin_m)
        r = int(round(margin_m / CELL))
        inner = np.zeros_like(area)
        inner[50 + r:150 - r, 50 + r:150 - r] = True
        # the square shrunk by the margin, its gaps closed; the disk's corners round the square's corners
        assert area[100, 100] and area[81, 120]
        assert not area[~inner].any()
        core = inner.copy()
        core[:50 + 2 * r + 1, :] = core[150 - 2 * r - 1:, :] = False
        assert area[core].all()
    assert COVERAGE_CLOSING_M <= 1.0


def test_map_inputs_give_windows_with_the_tiles_coverage(tmp_path):
    """Through the published map: the fetched window's coverage is the tiles' point_count, shrunk by the margin,
    on the raster's lattice (tile (0, 2) of the synthetic map saw no ground east of 80 m)."""
    from mapformat.loader import open_map
    from stages.evaluate.mcl_params import MarkingLikelihood
    from stages.tiles.compute import compute
    from tests.stages.tiles.tiles_synth import (
        UNSURVEYED_EAST_M,
        building_corners,
        buildings,
        city_context,
        corner_table,
    )

    xy, dirs, _ = building_corners(buildings())
    compute(city_context(tmp_path, corner_table(xy, dirs, seed=2, noise_m=0.0)))
    reader = open_map(tmp_path / "maps" / "city")
    gnss = np.array([[50.0, 250.0, 0.0]])
    _, fetch = map_inputs(reader, gnss, sensor_range_m=30.0, field=MarkingLikelihood(), coverage_margin_m=2.0)
    raster = fetch(60.0, 220.0, 100.0, 260.0)
    assert raster.observed.shape == raster.values.shape
    east = raster.origin_en_m[0] + (np.arange(raster.values.shape[1]) + 0.5) * raster.cell_m
    assert raster.observed[:, east < UNSURVEYED_EAST_M - 2.0 - reader.cell_m].all()
    assert not raster.observed[:, east > UNSURVEYED_EAST_M - 2.0 + reader.cell_m].any()
    _, plain = map_inputs(reader, gnss, sensor_range_m=30.0, field=MarkingLikelihood())
    assert plain(60.0, 220.0, 100.0, 260.0).observed is None
