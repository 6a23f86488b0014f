"""Known synthetic scenes -> known corners (ray-cast HDL-32E-like scans with 2 cm range noise)."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.corners import Building, Scene, TreeCrown, box_building, cast_scan, polygon_interior_angles_rad
from stages.corners.core import extract_corners, trace_corners
from stages.corners.lines import LINE
from stages.corners.params import CornerParams


def to_world(corners, pose):
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    xw = x + c * corners.x_m - s * corners.y_m
    yw = y + s * corners.x_m + c * corners.y_m
    return np.column_stack([xw, yw]), corners.theta1_rad + yaw, corners.theta2_rad + yaw


def angle_err_deg(a, b):
    return np.degrees(np.abs((np.asarray(a) - b + np.pi) % (2 * np.pi) - np.pi))


BOX = box_building((0.0, 0.0), (12.0, 8.0), yaw_rad=0.4, height_m=14.0)


@pytest.mark.parametrize("k", range(8))
def test_box_corners_within_2cm_and_half_degree_from_several_poses(k):
    # poses on the box's diagonals (where two walls of a corner are visible), radius 16-28 m
    rng = np.random.default_rng(100 + k)
    bearing = 0.4 + np.pi / 4 + (k % 4) * np.pi / 2 + rng.uniform(-0.25, 0.25)
    dist = 16.0 + 12.0 * (k // 4) + rng.uniform(0, 2)
    pose = (dist * np.cos(bearing), dist * np.sin(bearing), rng.uniform(-np.pi, np.pi))
    pts, ring = cast_scan(Scene([BOX]), pose, range_sigma_m=0.02, seed=k)
    corners = extract_corners(pts, ring)
    assert len(corners) >= 1, f"pose {pose}: no corner found"
    xy, th1, th2 = to_world(corners, pose)
    verts = BOX.footprint_xy_m
    d = np.linalg.norm(xy[:, None, :] - verts[None], axis=2)
    nearest = d.argmin(axis=1)
    assert d.min(axis=1).max() < 0.02, f"pose {pose}: corner errors {d.min(axis=1)} m"
    for i, v in enumerate(nearest):
        prev_v, next_v = verts[v - 1], verts[(v + 1) % len(verts)]
        walls = np.arctan2(*(np.array([prev_v, next_v]) - verts[v])[:, ::-1].T)
        e1 = angle_err_deg(th1[i], walls).min()
        e2 = angle_err_deg(th2[i], walls).min()
        assert e1 < 0.5 and e2 < 0.5, f"wall direction errors {e1:.3f}, {e2:.3f} deg"
        assert angle_err_deg(th1[i], th2[i]) > 80.0
    assert np.all(np.abs(np.degrees(corners.interior_angle_rad) - 90.0) < 0.5)
    assert np.all(corners.convex)
    assert np.all(corners.n_layers >= 3)
    np.testing.assert_allclose(corners.range_m, np.hypot(corners.x_m, corners.y_m))


LONG_WALL = Building(np.array([[-100.0, 10.0], [100.0, 10.0], [100.0, 11.0], [-100.0, 11.0]]), 12.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flat_wall_gives_no_corner(seed):
    pts, ring = cast_scan(Scene([LONG_WALL]), (0.0, 0.0, 0.3 * seed), seed=seed)
    trace = trace_corners(pts, ring)
    assert np.count_nonzero(trace.line_label == LINE) >= 8  # the wall is seen, on every layer
    assert len(trace.corners) == 0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("depth_m", [0.05, 0.2])
def test_tree_crowns_beside_a_wall_give_no_corner(seed, depth_m):
    trees = [TreeCrown((5.0, 8.0, 5.0), 2.5, 0.95, depth_m), TreeCrown((-3.0, 7.0, 4.5), 2.0, 0.95, depth_m)]
    pts, ring = cast_scan(Scene([LONG_WALL], trees), (0.0, 0.0, 0.0), seed=seed)
    trace = trace_corners(pts, ring)
    assert np.count_nonzero(trace.line_label != LINE) > 0  # leaf fragments were seen and rejected
    assert len(trace.corners) == 0


def test_outlier_test_rejects_rough_line_that_a_loose_threshold_keeps():
    # a hedge-like rough surface: a straight run with 0.08 m perpendicular scatter
    trees = []
    rough = Scene([LONG_WALL], trees)
    pts, ring = cast_scan(rough, (0.0, 0.0, 0.0), range_sigma_m=0.08, seed=5)
    loose = CornerParams(lines={"split_distance_m": 0.5, "max_residual_var_m2": 1.0})
    strict = CornerParams(lines={"split_distance_m": 0.5})
    lab_loose = trace_corners(pts, ring, loose).line_label
    lab_strict = trace_corners(pts, ring, strict).line_label
    assert np.count_nonzero(lab_loose == LINE) > 0
    assert np.count_nonzero(lab_strict == LINE) < np.count_nonzero(lab_loose == LINE)


def test_chamfered_obtuse_135_degree_corners_are_found():
    fp = np.array([[13.0, 5.0], [20.0, 5.0], [20.0, 15.0], [10.0, 15.0], [10.0, 8.0]])
    assert np.allclose(np.degrees(polygon_interior_angles_rad(fp))[[0, 4]], 135.0)
    pts, ring = cast_scan(Scene([Building(fp, 12.0)]), (0.0, 0.0, 0.0), seed=3)
    corners = extract_corners(pts, ring)
    xy = np.column_stack([corners.x_m, corners.y_m])
    for vertex in fp[[0, 4]]:
        d = np.linalg.norm(xy - vertex, axis=1)
        i = int(d.argmin())
        assert d[i] < 0.03
        assert abs(np.degrees(corners.interior_angle_rad[i]) - 135.0) < 0.5
        assert corners.convex[i]


def test_concave_inner_corner_is_told_apart():
    fp = np.array([[10, 5], [30, 5], [30, 10], [15, 10], [15, 25], [10, 25]], float)
    pose = (25.0, 20.0, 0.0)
    corners = extract_corners(*cast_scan(Scene([Building(fp, 12.0)]), pose, seed=3))
    xy, _, _ = to_world(corners, pose)
    d = np.linalg.norm(xy - [15.0, 10.0], axis=1)
    i = int(d.argmin())
    assert d[i] < 0.03
    assert not corners.convex[i]
    assert abs(np.degrees(corners.interior_angle_rad[i]) - 90.0) < 0.5


def test_near_flat_corner_has_large_elongated_covariance():
    # a 160 deg corner vs a 90 deg corner seen from the same distance (paper Figure 26)
    params = CornerParams(candidates={"max_interior_angle_deg": 170.0})
    a = np.radians(10.0)
    flat = np.array([[15.0, -10.0], [15.0, 0.0], [15.0 + 10 * np.sin(2 * a), 10 * np.cos(2 * a)], [30.0, 10.0],
                     [30.0, -10.0]])
    square = np.array([[15.0, -10.0], [15.0, 0.0], [25.0, 0.0], [30.0, 10.0], [30.0, -10.0]])
    sig = {}
    for name, fp in (("flat", flat), ("square", square)):
        trace = trace_corners(*cast_scan(Scene([Building(fp, 12.0)]), (0.0, 8.0, 0.0), seed=4), params)
        cand = trace.candidates
        i = np.linalg.norm(np.column_stack([cand.x_m, cand.y_m + 8.0]) - [15.0, 0.0], axis=1) < 0.5
        assert i.any(), f"{name}: no candidate at the corner"
        ev = np.linalg.eigvalsh(cand.cov_m2[i])
        assert np.all(ev > 0)
        sig[name] = np.sqrt(ev.max(axis=1)).mean(), (ev.max(axis=1) / ev.min(axis=1)).mean()
    assert sig["flat"][0] > 3 * sig["square"][0]
    assert sig["flat"][1] > 10.0  # elongated


@pytest.mark.parametrize("dist_m", [10.0, 15.0, 22.0])
def test_a_truck_sized_box_gives_no_corner_but_a_building_of_the_same_footprint_does(dist_m):
    truck = box_building((0.0, 0.0), (10.0, 2.5), yaw_rad=0.3, height_m=3.6)  # 1.8 m above the sensor
    house = box_building((0.0, 0.0), (10.0, 2.5), yaw_rad=0.3, height_m=9.0)
    corner = truck.footprint_xy_m[0]
    away = (corner + [0.0, -3.0]) / np.linalg.norm(corner + [0.0, -3.0])
    pose = (*(corner + dist_m * away), 0.0)  # the corner at about dist_m, both walls in view
    # a tall building behind the sensor: every upper ring has returns somewhere, as in a street
    behind = box_building(tuple(corner + (dist_m + 30.0) * away), (20.0, 20.0), 0.3, 40.0)
    scan = cast_scan(Scene([truck, behind]), pose, seed=1)
    target = corner - np.asarray(pose[:2])  # the truck's corner in the sensor frame (sensor yaw 0)

    def near(x, y):
        return np.hypot(x - target[0], y - target[1]) < 0.5

    trace = trace_corners(*scan)
    seen = near(trace.candidates.x_m, trace.candidates.y_m)
    assert seen.sum() >= 3 and (trace.candidate_corner[seen] < 0).all()  # candidates were seen ...
    assert not near(trace.corners.x_m, trace.corners.y_m).any()  # ... but a higher beam passed over the box
    unchecked = extract_corners(*scan, CornerParams(checks={"max_passover_height_m": 0}))
    assert near(unchecked.x_m, unchecked.y_m).any()
    house = extract_corners(*cast_scan(Scene([house, behind]), pose, seed=1))
    assert near(house.x_m, house.y_m).any()
