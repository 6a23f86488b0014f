"""Unit oracles of the building blocks: ordering, breaks, IEPF, TLS, candidates, the redundancy check."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fixtures.corners import HDL32E_ELEVATION_DEG, Scene, box_building, cast_scan
from stages.corners.candidates import CornerCandidates, find_corner_candidates
from stages.corners.determine import determine_corners, floor_covariance
from stages.corners.layers import estimate_ring_elevation_deg, find_run_starts, order_rings_by_azimuth, select_layers
from stages.corners.lines import extract_lines, fit_lines_tls, split_iepf
from stages.corners.params import CornerParams


def polyline_points(vertices, spacing_m=0.05):
    pts = []
    for a, b in zip(vertices[:-1], vertices[1:]):
        n = int(np.ceil(np.linalg.norm(np.subtract(b, a)) / spacing_m))
        pts.append(np.linspace(a, b, n, endpoint=False))
    pts.append(np.asarray(vertices[-1:], float))
    return np.concatenate(pts)


def test_iepf_splits_a_noiseless_polyline_exactly_at_its_vertices():
    verts = [(10.0, -5.0), (10.0, 0.0), (14.0, 0.0), (17.0, 3.0), (17.0, 8.0)]
    xy = polyline_points(verts)
    start, stop = split_iepf(xy, np.array([0]), np.array([len(xy) - 1]), split_distance_m=0.01, min_points=3)
    assert len(start) == 4
    np.testing.assert_allclose(xy[start], verts[:-1], atol=1e-9)
    np.testing.assert_allclose(xy[stop], verts[1:], atol=1e-9)


def test_tls_fit_matches_an_svd_fit():
    rng = np.random.default_rng(7)
    t = rng.uniform(-3, 3, 200)
    normal = 0.7
    n = np.array([np.cos(normal), np.sin(normal)])
    xy = np.outer(t, [-n[1], n[0]]) + 12.0 * n + rng.normal(0, 0.03, 200)[:, None] * n
    lines = fit_lines_tls(xy, np.zeros(200, int), np.array([0]), np.array([199]))
    c = xy.mean(axis=0)
    _, s, vt = np.linalg.svd(xy - c)
    n_svd = vt[1] * np.sign(vt[1] @ n)
    n_fit = np.array([np.cos(lines.normal_rad[0]), np.sin(lines.normal_rad[0])])
    n_fit *= np.sign(n_fit @ n)
    np.testing.assert_allclose(n_fit, n_svd, atol=1e-9)
    assert abs(abs(lines.offset_m[0]) - abs(n_svd @ c)) < 1e-9
    np.testing.assert_allclose(lines.residual_var_m2[0], s[1] ** 2 / 200, rtol=1e-6)
    np.testing.assert_allclose(lines.spread_m2[0], s[0] ** 2, rtol=1e-6)
    assert abs(np.sqrt(lines.residual_var_m2[0]) - 0.03) < 0.005


def test_runs_break_at_range_jumps_and_azimuth_gaps_but_not_along_a_wall():
    az = np.radians(np.r_[np.arange(0, 10, 0.2), np.arange(12, 20, 0.2)])  # a 2 deg gap at 10 deg
    r = np.where(az < np.radians(5), 10.0, 15.0)  # a 5 m range jump at 5 deg
    r = np.where(az > np.radians(11), 10.0 / np.cos(az - np.radians(16)), r)  # a flat wall facing the sensor
    xy = np.column_stack([r * np.cos(az), r * np.sin(az)])
    starts = find_run_starts(xy, np.zeros(len(xy), int), break_incidence_deg=10.0, range_sigma_m=0.03,
                             max_azimuth_gap_deg=1.0)
    np.testing.assert_array_equal(np.degrees(az[starts]).round(1), [0.0, 5.0, 12.0])


def test_rings_are_ordered_by_azimuth_starting_after_the_widest_gap():
    rng = np.random.default_rng(3)
    az = np.radians(np.r_[np.arange(150, 180, 0.5), np.arange(-180, -150, 0.5)])  # a wall behind the sensor
    xy = np.column_stack([20 * np.cos(az), 20 * np.sin(az)])
    layer = np.r_[np.zeros(len(az), int), np.ones(len(az), int)]
    xy2 = np.r_[xy, xy]
    shuffle = rng.permutation(len(xy2))
    order = order_rings_by_azimuth(xy2[shuffle], layer[shuffle])
    out_az = np.degrees(np.arctan2(xy2[shuffle][order, 1], xy2[shuffle][order, 0]))
    out_layer = layer[shuffle][order]
    assert np.all(np.diff(out_layer) >= 0)
    for k in (0, 1):
        a = out_az[out_layer == k]
        assert a[0] == pytest.approx(150.0) and a[-1] == pytest.approx(-150.5)
        assert np.all(np.diff(np.unwrap(np.radians(a))) > 0)


LAYERS = CornerParams().layers  # the stage's layer selection


def layer_args(**changes) -> dict:
    """``select_layers``' settings: the stage's, some changed."""
    return {"mode": LAYERS.layer_selection, "n_upper_layers": LAYERS.n_upper_layers,
            "min_elevation_deg": LAYERS.min_elevation_deg, "min_range_m": LAYERS.min_range_m, **changes}


def test_layer_selection_by_elevation_and_by_index():
    pts, ring = cast_scan(Scene([box_building((15, 0), (30, 60), 0.0, 40.0)]), (0, 0, 0), seed=1)
    ids, elev = estimate_ring_elevation_deg(pts, ring, min_range_m=LAYERS.min_range_m)
    np.testing.assert_allclose(elev, HDL32E_ELEVATION_DEG[ids], atol=0.05)
    np.testing.assert_array_equal(select_layers(pts, ring, **layer_args()), np.arange(31, 23, -1))
    np.testing.assert_array_equal(select_layers(pts, ring, **layer_args(min_elevation_deg=5.5)), [31, 30, 29, 28])
    np.testing.assert_array_equal(select_layers(pts, ring, **layer_args(mode="top_n", n_upper_layers=3)),
                                  [31, 30, 29])
    with pytest.raises(ValueError, match="ring indices must be >= 0"):
        select_layers(pts, np.full(len(ring), -1), **layer_args())
    with pytest.raises(ValueError, match="'elevation' or 'top_n'"):
        select_layers(pts, ring, **layer_args(mode="median"))


def test_ring_elevation_from_a_sample_equals_the_full_estimate_and_keeps_sparse_rings():
    pts, ring = cast_scan(Scene([box_building((15, 0), (30, 60), 0.0, 40.0)]), (0, 0, 0), seed=1)
    order = np.argsort(np.arange(len(ring)) % 7, kind="stable")  # another point order than the firing order
    pts, ring = pts[order], ring[order]
    sparse = np.flatnonzero(ring == 30)[:20]  # ring 30 keeps 20 points: too few to be sampled reliably
    keep = np.ones(len(ring), bool)
    keep[np.flatnonzero(ring == 30)] = False
    keep[sparse] = True
    pts, ring = pts[keep], ring[keep]
    ids_full, elev_full = estimate_ring_elevation_deg(pts, ring, min_range_m=LAYERS.min_range_m, max_points=0)
    ids, elev = estimate_ring_elevation_deg(pts, ring, min_range_m=LAYERS.min_range_m, max_points=3000)
    np.testing.assert_array_equal(ids, ids_full)
    np.testing.assert_allclose(elev, elev_full, atol=0.05)
    np.testing.assert_allclose(elev[ids == 30], elev_full[ids_full == 30], atol=1e-12)  # from all of its points
    np.testing.assert_allclose(elev, HDL32E_ELEVATION_DEG[ids], atol=0.1)
    np.testing.assert_array_equal(select_layers(pts, ring, **layer_args()), np.arange(31, 23, -1))


def _candidates(xy, layer, cov_sigma):
    m = len(xy)
    cov = np.repeat(np.eye(2)[None], m, axis=0) * np.asarray(cov_sigma, float)[:, None, None] ** 2
    z = np.zeros(m)
    return CornerCandidates(x_m=xy[:, 0], y_m=xy[:, 1], theta1_rad=z + 0.1, theta2_rad=z + 1.6, cov_m2=cov,
                            layer=np.asarray(layer), interior_angle_rad=z + 1.5, convex=np.ones(m, bool),
                            line_a=np.arange(m), line_b=np.arange(m), vertex_gap_spacings=z)


def test_redundancy_check_keeps_multi_layer_corners_and_drops_single_layer_ones():
    xy = np.array([[10.0, 5.0], [10.02, 5.0], [10.0, 5.04], [30.0, 0.0], [10.01, 5.01]])
    cand = _candidates(xy, [1, 2, 3, 1, 3], [0.02] * 5)
    corners, corner_of = determine_corners(cand, cluster_radius_m=0.3, cluster_max_angle_rad=0.26, min_layers=3,
                                           min_sigma_m=0.01)
    assert len(corners) == 1
    np.testing.assert_array_equal(corner_of, [0, 0, 0, -1, 0])
    assert corners.n_layers[0] == 3
    np.testing.assert_allclose([corners.x_m[0], corners.y_m[0]], xy[[0, 1, 2, 4]].mean(axis=0), atol=1e-12)
    assert np.isnan(corners.time_offset_s[0])


def test_fusion_is_information_weighted_and_its_covariance_is_floored():
    xy = np.array([[10.0, 5.0], [10.1, 5.0], [10.0, 5.1]])
    cand = _candidates(xy, [1, 2, 3], [0.01, 0.1, 0.1])
    corners, _ = determine_corners(cand, cluster_radius_m=0.3, cluster_max_angle_rad=0.26, min_layers=3,
                                   min_sigma_m=0.01, time_offset_s=np.array([0.01, 0.02, 0.03]))
    w = np.array([100.0, 1.0, 1.0])
    np.testing.assert_allclose([corners.x_m[0], corners.y_m[0]], w @ xy / w.sum(), atol=1e-12)
    assert np.linalg.eigvalsh(corners.cov_m2[0]).min() >= 0.01 ** 2 - 1e-15
    assert corners.time_offset_s[0] == pytest.approx(0.02)
    tight, _ = determine_corners(cand, cluster_radius_m=0.3, cluster_max_angle_rad=0.26, min_layers=4,
                                 min_sigma_m=0.01)
    assert len(tight) == 0


def test_candidates_need_their_intersection_near_both_facing_ends():
    # two walls meeting at (10, 0) but the second starts 2 m away from the corner (an occluded corner)
    wall_a = polyline_points([(10.0, -6.0), (10.0, -0.05)])
    for gap, expected in ((0.1, 1), (2.0, 0)):
        wall_b = polyline_points([(10.0 + gap, 0.0), (16.0, 0.0)])
        xy = np.r_[wall_a, wall_b]
        lines = fit_lines_tls(xy, np.zeros(len(xy), int), np.array([0, len(wall_a)]),
                              np.array([len(wall_a) - 1, len(xy) - 1]))
        cand = find_corner_candidates(lines, xy, max_corner_gap_m=0.6, min_interior_angle_rad=np.radians(50),
                                      max_interior_angle_rad=np.radians(155), line_sigma_floor_m=0.01)
        assert len(cand) == expected
    np.testing.assert_allclose([cand.x_m, cand.y_m] if len(cand) else [[10.0], [0.0]], [[10.0], [0.0]], atol=1e-9)


def test_extract_lines_on_an_empty_ring_returns_no_line():
    lines = extract_lines(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, np.int64), split_distance_m=0.1,
                          min_points=6, merge_max_angle_rad=0.03, end_trim_points=1)
    assert len(lines) == 0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=4, max_size=4),
       st.floats(1e-4, 1.0))
def test_floored_covariance_is_symmetric_positive_definite(values, floor_m):
    cov = np.array(values, float).reshape(1, 2, 2)
    out = floor_covariance(cov, floor_m)
    np.testing.assert_allclose(out, np.swapaxes(out, 1, 2), atol=1e-9 * max(1.0, np.abs(out).max()))
    assert np.linalg.eigvalsh(out).min() >= floor_m ** 2 * (1 - 1e-6) - 1e-12 * np.abs(out).max()


def test_mismatched_or_malformed_inputs_are_rejected_with_shapes_in_the_message():
    from stages.corners.core import extract_corners

    with pytest.raises(ValueError, match=r"points \(5, 2\)"):
        extract_corners(np.zeros((5, 2)), np.zeros(5, int))
    with pytest.raises(ValueError, match=r"ring \(4,\)"):
        extract_corners(np.zeros((5, 3)), np.zeros(4, int))
    empty = extract_corners(np.zeros((0, 3), np.float32), np.zeros(0, np.int16))
    assert len(empty) == 0
