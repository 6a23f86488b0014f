"""Vertical ground registration (height, roll, pitch with the horizontal pose held): synthetic street with known
truth, started far off in height and tilt, with kerbs, parked cars and a horizontal error in the start."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy
from stages.posegraph.anchors.ground_registration import plane_normals, register_vertical
from stages.posegraph.anchors.survey_anchor import anchor_scan, build_survey_index
from tests.stages.posegraph.conftest import posegraph_config


def _ground_m(e: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A sloped street (2 % east, 1 % north, a 3 cm crown across) with 15 cm kerbs at |north| > 6 m."""
    return 0.02 * e + 0.01 * n - 0.03 * (n / 6.0) ** 2 + 0.15 * (np.abs(n) > 6.0)


def _street(rng):
    e, n = np.meshgrid(np.arange(-60, 60, 0.1), np.arange(-20, 20, 0.1))
    survey = np.column_stack([e.ravel(), n.ravel(), _ground_m(e.ravel(), n.ravel())])
    x0, y0, yaw = 3.0, 1.0, 0.2
    up = np.array([-0.02, -0.01 + 0.06 * y0 / 36.0, 1.0])  # the street's normal under the vehicle
    up /= np.linalg.norm(up)
    x = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    x -= up * (x @ up)
    x /= np.linalg.norm(x)
    T_true = np.eye(4)
    T_true[:3, :3] = np.column_stack([x, np.cross(up, x), up])
    T_true[:3, 3] = [x0, y0, float(_ground_m(np.array(x0), np.array(y0)))]
    near = survey[np.hypot(survey[:, 0] - x0, survey[:, 1] - y0) < 25.0][::3]
    cars = []  # parked cars along the kerb: 4 x 1.8 m boxes, points 0.3-0.5 m above the road
    for ce in (-15.0, -5.0, 8.0, 17.0):
        pts = rng.uniform([ce - 2.0, 4.0, 0.3], [ce + 2.0, 5.8, 0.5], (400, 3))
        pts[:, 2] += _ground_m(pts[:, 0], pts[:, 1])
        cars.append(pts)
    seen = np.vstack([near, *cars]) + rng.normal(0, 0.01, (len(near) + 1600, 3))
    scan = (seen - T_true[:3, 3]) @ T_true[:3, :3]  # the vehicle's view
    return survey, scan, T_true


def _tilt_deg(A, B):
    return float(np.rad2deg(np.arccos(np.clip(A[:3, 2] @ B[:3, 2], -1, 1))))


@pytest.mark.parametrize("start", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1.4, 0.5), (0.4, -0.3, -0.6, -0.4)])
def test_height_and_tilt_recovered_from_far_off_starts(start):
    """From 1.4 m and 0.5 deg off (beyond a 1 m correspondence distance) the height comes within 5 mm and the tilt
    within 0.03 deg of the truth; a 0.5 m horizontal error in the start is kept (x, y and heading are not moved)."""
    rng = np.random.default_rng(3)
    survey, scan, T_true = _street(rng)
    de, dn, dz, dtilt_deg = start
    T0 = T_true @ se3_from_xyz_rpy(0.0, 0.0, 0.0, np.deg2rad(dtilt_deg), np.deg2rad(-dtilt_deg), 0.0)
    T0[:3, 3] += [de, dn, dz]
    origin = T0[:3, 3].copy()
    crop = survey[np.hypot(survey[:, 0] - origin[0], survey[:, 1] - origin[1]) < 40.0] - origin
    T_local = T0.copy()
    T_local[:3, 3] -= origin
    fit = register_vertical(scan, crop, plane_normals(crop), T_local)
    T = fit.T_target_source.copy()
    T[:3, 3] += origin
    assert fit.converged and fit.fitness > 0.9 and fit.inlier_rmse_m < 0.1
    ground_here = float(_ground_m(np.array(T[0, 3]), np.array(T[1, 3])))
    assert abs(T[2, 3] - ground_here) < 0.005, T[2, 3] - ground_here
    assert _tilt_deg(T, T_true) < 0.03
    np.testing.assert_allclose(T[:2, 3], T0[:2, 3], atol=0.01)  # horizontal position held
    yaw = lambda A: np.arctan2(A[1, 0], A[0, 0])  # noqa: E731
    assert abs(yaw(T) - yaw(T0)) < 5e-4  # second order in the 0.5 deg tilt step (vertical_part keeps it exactly)


@pytest.mark.parametrize("survey_normals", ["per crop", "whole survey"])
def test_a_start_beyond_the_correspondence_distance_is_anchored(survey_normals):
    """The keyframe anchor from an estimate 1.4 m too high: accepted and on the ground, where a registration bounded
    by its 1 m correspondence distance found nothing to pair; the same with the survey's normals computed once for
    the whole survey (the stage's workers) as with each crop's."""
    from stages.posegraph.anchors.survey_anchor import survey_plane_normals

    rng = np.random.default_rng(5)
    survey, scan, T_true = _street(rng)
    cfg = posegraph_config().anchors.ground
    pts, tree = build_survey_index(survey, cfg.voxel_m)
    T0 = T_true.copy()
    T0[:3, 3] += [0.3, 0.3, 1.4]
    normals = survey_plane_normals(pts) if survey_normals == "whole survey" else None
    m = anchor_scan(0, scan, T0, pts, tree, cfg, normals)
    assert m.accepted, m.reason
    assert abs(m.T_map_vehicle[2, 3] - _ground_m(np.array(T0[0, 3]), np.array(T0[1, 3]))) < 0.01
    assert _tilt_deg(m.T_map_vehicle, T_true) < 0.05
    if normals is not None:  # within a tenth of a millimetre / thousandth of a degree of the per-crop result
        per_crop = anchor_scan(0, scan, T0, pts, tree, cfg)
        assert abs(m.T_map_vehicle[2, 3] - per_crop.T_map_vehicle[2, 3]) < 1e-4
        assert _tilt_deg(m.T_map_vehicle, per_crop.T_map_vehicle) < 1e-3


def test_no_ground_is_not_converged():
    rng = np.random.default_rng(0)
    wall = rng.uniform([-10, 5, 0], [10, 5.2, 10], (3000, 3))  # a facade only
    survey = rng.uniform([-30, -30, 0], [30, 30, 0.01], (20000, 3))
    fit = register_vertical(wall + [0, 0, 5.0], survey, plane_normals(survey), np.eye(4), max_corr_m=1.0)
    assert fit.fitness < 0.1 or not fit.converged
