"""Vectorized road markings: a painted two-lane city (the simulator's own painting) -> typed features scored
against the simulator's typed truth; clipping and scoring on known geometry."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.marking_scores import sample_polyline, score_markings
from stages.common.marking_vectors import TYPES, clip_polyline_to_box, vectorize_markings
from stages.simulate.markings import (
    city_from_description,
    generate_markings,
    marking_truth_features,
    rasterize_markings,
)

CITY = {"intersections_en": [[[0, 0], [120, 0], [240, 0]], [[0, 100], [120, 100], [240, 100]]],
        "road_half_width_m": {"east_west": 9.0, "north_south": 9.0},
        "lanes_per_direction": {"east_west": 2, "north_south": 2}}


@pytest.fixture(scope="module")
def painted():
    city = city_from_description(CITY)
    raster = rasterize_markings(generate_markings(city), city.bounds_en)
    return raster, marking_truth_features(city)


@pytest.mark.parametrize("dropout", [0.0, 0.4])
def test_every_type_is_found_where_it_is_painted(painted, dropout):
    raster, truth = painted
    mask = (raster.data > 0) & (np.random.default_rng(3).random(raster.data.shape) >= dropout)
    south = raster.north_m - mask.shape[0] * raster.res_m
    feats = vectorize_markings(mask, raster.west_m, south, raster.res_m)
    scores = score_markings([(f.type, f.xy_m) for f in feats], truth, tol_m=0.3)
    assert {k for k, _ in truth} == set(TYPES)  # the oracle has every type
    for kind in TYPES:
        assert scores[kind]["precision"] >= 0.95 and scores[kind]["recall"] >= 0.95, (kind, scores[kind])


def test_scores_fall_when_geometry_is_off_or_mistyped(painted):
    _, truth = painted
    assert all(v["precision"] == 1.0 and v["recall"] == 1.0 for v in score_markings(truth, truth).values())
    shifted = [(k, xy + [0.0, 1.0]) if k in ("lane_solid", "crosswalk") else (k, xy) for k, xy in truth]
    s = score_markings(shifted, truth, tol_m=0.3)
    assert s["lane_solid"]["precision"] < 0.5 and s["stop_line"]["recall"] == 1.0
    retyped = [("lane_dashed" if k == "lane_solid" else k, xy) for k, xy in truth]
    s = score_markings(retyped, truth)
    assert s["lane_solid"]["recall"] == 0.0 and s["lane_dashed"]["precision"] < 0.5


def test_clip_polyline_to_box():
    line = np.array([[-10.0, 5.0], [5.0, 5.0], [5.0, 20.0]])
    [part] = clip_polyline_to_box(line, 0.0, 0.0, 10.0, 10.0)
    np.testing.assert_allclose(part, [[0.0, 5.0], [5.0, 5.0], [5.0, 10.0]])
    assert clip_polyline_to_box(np.array([[20.0, 0.0], [30.0, 0.0]]), 0.0, 0.0, 10.0, 10.0) == []
    zigzag = np.array([[1.0, 1.0], [1.0, 15.0], [2.0, 15.0], [2.0, 1.0]])
    assert len(clip_polyline_to_box(zigzag, 0.0, 0.0, 10.0, 10.0)) == 2
    assert len(sample_polyline(np.array([[0.0, 0.0], [1.0, 0.0]]), 0.25)) == 5


@pytest.mark.parametrize("angle_deg", [0.0, 7.0, 33.0])
def test_crosswalk_corners_from_a_sampled_raster_within_4_cm(angle_deg):
    """Six stripes 4 m x 0.5 m at 1 m pitch, turned by angle_deg, sampled like a lidar raster: one random point
    per 0.1 m cell decides whether the cell is paint. The corners are recovered to 4 cm (the box around the pixel
    centres, used before, put its sides 4-9 cm out on average, up to 13 cm)."""
    rng = np.random.default_rng(int(angle_deg))
    a = np.radians(angle_deg)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    origin = np.array([5.03, 4.07])
    cell, n = 0.1, 200
    xy = (np.stack(np.meshgrid(np.arange(n), np.arange(n)[::-1]), -1) + rng.uniform(0, 1, (n, n, 2))) * cell
    s, t = (xy - origin) @ u, (xy - origin) @ v  # stripes along u, stacked along v
    mask = ((s >= 0) & (s <= 4.0) & (t >= 0) & (t <= 5.5) & (np.mod(t, 1.0) <= 0.5)).astype(np.uint8) * 255
    [cw] = [f for f in vectorize_markings(mask, 0.0, 0.0, cell) if f.type == "crosswalk"]
    truth = origin + np.array([[0, 0], [4.0, 0], [4.0, 5.5], [0, 5.5]]) @ np.vstack([u, v])
    err = [np.linalg.norm(truth - p, axis=1).min() for p in cw.xy_m]
    assert max(err) <= 0.04, err
    assert abs(cw.width_m - 4.0) <= 0.03 and abs(cw.length_m - 5.5) <= 0.03
