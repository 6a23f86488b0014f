"""Localizability prediction (stages/common/localizability*.py, corner_visibility.py, marking_information.py):
oracles on known geometry, a cross-check of the covariance recursion against the evaluate stage's own EKF, and the
consider states' floor."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.corner_visibility import occluded, side_visible, visible, wall_segments
from stages.common.localizability import Corners, LocalizabilityConfig, predict_pass, resample_path
from stages.common.localizability_cells import corners_in_view, predict_cells
from stages.common.marking_information import likelihood_field, marking_information

Q1 = np.array([[0.0, np.pi / 2]])  # walls along +east and +north: a building in the north-east quadrant


def test_an_outside_corner_is_seen_from_the_opposite_quadrant_only_an_inside_one_from_its_own():
    pts = np.array([[-10.0, -10.0], [10.0, -10.0], [-10.0, 10.0], [5.0, 5.0], [-10.0, -0.5]])
    convex = side_visible(pts, np.zeros((1, 2)), Q1, np.array([True]), np.deg2rad(10))[:, 0]
    inside = side_visible(pts, np.zeros((1, 2)), Q1, np.array([False]), np.deg2rad(10))[:, 0]
    # (-10, -0.5) sees the east wall at 2.9 deg: too grazing for a line
    assert convex.tolist() == [True, False, False, False, False]
    assert inside.tolist() == [False, False, False, True, False]


def test_a_wall_between_hides_a_corner_and_walls_pair_between_corners():
    # two corners of one building face 20 m long along east, seen from the south; a third corner behind the face
    corners = np.array([[0.0, 0.0], [20.0, 0.0], [10.0, 10.0]])
    theta = np.array([[0.0, np.pi / 2], [np.pi, np.pi / 2], [-np.pi / 2, 0.0]])
    segs = wall_segments(corners, theta, stub_m=5.0)
    face = [s for s in segs if np.allclose(sorted(s[:, 0]), [0.0, 20.0]) and np.allclose(s[:, 1], 0.0)]
    assert len(face) == 1  # the face is one wall from corner 0 to corner 1, not two stubs
    blocked = occluded(np.array([[10.0, -20.0]]), corners, segs)[0]
    assert blocked.tolist() == [False, False, True]
    vis = visible(np.array([[-10.0, -10.0]]), corners, theta, np.array([True, True, True]), range_m=60.0,
                  segments=segs)[0]
    assert vis.tolist() == [True, False, False]  # corner 1 shows its far wall's back; corner 2 is behind the face


def _window_of(mask: np.ndarray, cell: float):
    h = mask.shape[0]

    def window(e0, n0, e1, n1):
        c0, c1 = int(np.floor(e0 / cell)), int(np.ceil(e1 / cell))
        s0, s1 = int(np.floor(n0 / cell)), int(np.ceil(n1 / cell))
        out = np.zeros((s1 - s0, c1 - c0), np.uint8)
        for s in range(max(s0, 0), min(s1, h)):
            for_cols = slice(max(c0, 0), min(c1, mask.shape[1]))
            row = mask[h - 1 - s, for_cols]
            out[s1 - 1 - s, max(c0, 0) - c0:max(c0, 0) - c0 + len(row)] = row
        return out, (c0 * cell, s0 * cell), cell

    return window


def test_an_unbroken_line_informs_across_only_and_dashes_inform_along_too():
    cell = 0.1
    solid = np.zeros((1000, 1000), np.uint8)  # 100 m square, row 0 north; a line along east at north = 50 m
    solid[1000 - 502:1000 - 500, :] = 255
    dashed = solid.copy()
    for e0 in range(0, 1000, 60):  # 3 m dashes, 3 m gaps
        dashed[:, e0 + 30:e0 + 60] = 0
    kw = dict(sigma_m=0.2, feature_range_m=30.0, sharpness=5.0, effective_points=60.0)
    p = np.array([[50.0, 48.0]])
    info_s, n_s = marking_information(p, _window_of(solid, cell), 100.0, **kw)
    info_d, n_d = marking_information(p, _window_of(dashed, cell), 100.0, **kw)
    assert n_s[0] > 500 and n_d[0] > 200
    assert info_s[0, 1, 1] > 1000 and info_s[0, 0, 0] < 1e-6 * info_s[0, 1, 1]  # across (north) only
    assert info_d[0, 0, 0] > 0.03 * info_d[0, 1, 1] and info_d[0, 0, 0] > 1e4 * max(info_s[0, 0, 0], 1e-9)  # dash ends
    assert np.all(np.linalg.eigvalsh(info_d[0]) >= -1e-9)
    field = likelihood_field(solid, cell, 0.2)
    assert field[1000 - 501, 10] == 1.0 and field[1000 - 501 + 2, 10] == pytest.approx(np.exp(-0.5), rel=1e-3)


def test_the_covariance_recursion_is_the_evaluate_stage_ekf_s_own():
    """With exact map corners and no markings, ``predict_pass`` is the EKF's predict + update (Joseph form) along
    the same path with the same noise: the evaluate stage's ekf.predict / ekf.update, step by step."""
    from stages.evaluate import ekf

    cfg = LocalizabilityConfig(detection_rate=1.0)
    corners = Corners(np.array([[20.0, 8.0], [40.0, -9.0], [65.0, 7.0]]), np.zeros((3, 2, 2)),
                      np.array([[0.0, np.pi / 2], [0.0, -np.pi / 2], [np.pi, np.pi / 2]]), np.ones(3, bool))
    pts, yaw = resample_path(np.array([[0.0, 0.0], [80.0, 0.0]]), 0.8)
    in_view = corners_in_view(pts, corners, cfg)
    assert max(len(v) for v in in_view) >= 2 and min(len(v) for v in in_view) == 0
    got = predict_pass(pts, yaw, 0.8, "ekf", corners, in_view, np.zeros((len(pts), 3, 3)), cfg)
    n = cfg.ekf
    s_xy = n.icp_sigma_frac * 0.8 + n.icp_sigma_xy_m
    Q = np.diag([s_xy ** 2, s_xy ** 2, np.deg2rad(n.icp_sigma_yaw_deg) ** 2])
    state = ekf.EkfState(np.array([0.0, 0.0, 0.0]), np.diag([n.init_sigma_xy_m ** 2] * 2
                                                             + [np.deg2rad(n.init_sigma_yaw_deg) ** 2]))
    R1 = np.diag([n.range_sigma_floor_m ** 2, np.deg2rad(n.bearing_sigma_floor_deg) ** 2])
    for k in range(len(pts)):
        if k:
            state = ekf.predict(ekf.EkfState(np.array([*pts[k - 1], yaw[k - 1]]), state.P), [0.8, 0.0, 0.0], Q)
        q = np.array([*pts[k], yaw[k]])
        state = ekf.EkfState(q, state.P)
        idx = in_view[k]
        if len(idx):
            z, _ = ekf.predict_range_bearing(q, corners.en_m[idx])
            state, _ = ekf.update(state, z, corners.en_m[idx], np.repeat(R1[None], len(idx), 0),
                                  np.full(2 * len(idx), yaw[k]), np.deg2rad(n.wall_heading_sigma_deg))
        np.testing.assert_allclose(got[k], state.P, rtol=1e-6, atol=1e-12)


def test_map_errors_shared_by_every_look_are_not_averaged_away():
    """Corners whose errors are one common offset (correlation share ~1): however many looks, the position's
    predicted covariance stays at the corners' (the consider states); independent errors of 4 corners average at
    best to a quarter of one corner's, never below, however many looks."""
    C = np.diag([0.05 ** 2, 0.05 ** 2])
    en = np.array([[10.0, 8.0], [25.0, -8.0], [40.0, 8.0], [55.0, -8.0]])
    theta = np.array([[0.0, np.pi / 2], [0.0, -np.pi / 2], [0.0, np.pi / 2], [0.0, -np.pi / 2]])
    corners = Corners(en, np.repeat(C[None], 4, 0), theta, np.ones(4, bool))
    pts, yaw = resample_path(np.array([[-30.0, 0.0], [0.0, 0.0]]), 0.8)
    common = LocalizabilityConfig(detection_rate=1.0, corr_share=0.999, corr_length_m=1e4)
    alone = LocalizabilityConfig(detection_rate=1.0, corr_share=0.0)
    args = (pts, yaw, 0.8, "ekf", corners, corners_in_view(pts, corners, common), np.zeros((len(pts), 3, 3)))
    P_common, P_alone = predict_pass(*args, common)[-1], predict_pass(*args, alone)[-1]
    assert P_common[0, 0] > 0.9 * C[0, 0] and P_common[1, 1] > 0.9 * C[1, 1]
    trace = lambda P: P[0, 0] + P[1, 1]
    assert 0.9 * np.trace(C) / 4 < trace(P_alone) < trace(P_common)


def test_cells_of_a_road_with_and_without_corners_name_the_weak_ones():
    """A 200 m street: corners along its first half, none along the second; no markings. The EKF's sigma grows
    where no corner is in view and those cells say so; the MCL without paint fails everywhere."""
    xs = np.arange(10.0, 100.0, 15.0)
    en = np.concatenate([np.column_stack([xs, np.full(len(xs), 8.0)]),
                         np.column_stack([xs + 7, np.full(len(xs), -8.0)])])
    theta = np.concatenate([np.tile([[0.0, np.pi / 2]], (len(xs), 1)), np.tile([[0.0, -np.pi / 2]], (len(xs), 1))])
    corners = Corners(en, np.repeat(np.diag([1e-4, 1e-4])[None], len(en), 0), theta, np.ones(len(en), bool))
    cols = predict_cells([np.column_stack([np.arange(0.0, 200.0, 0.8), np.zeros(250)])], corners, None,
                         LocalizabilityConfig())
    ekf = [k for k, m in enumerate(cols["method"]) if m == "ekf"]
    east = np.array(cols["east_m"])[ekf]
    s2d = np.array(cols["sigma_2d_m"])[ekf]
    status = np.array(cols["status"])[ekf]
    reason = np.array(cols["reason"])[ekf]
    near = (east > 30) & (east < 80)
    far = east > 170
    assert s2d[near].max() < 0.05 and s2d[far].min() > 3 * s2d[near].max()
    assert set(status[near]) == {"ok"} and all("no corner in view" in r for r in reason[far])
    mcl = [k for k, m in enumerate(cols["method"]) if m == "mcl"]
    assert set(np.array(cols["status"])[mcl][1:]) == {"fail"}
    assert len(set(zip(cols["cell_i"], cols["cell_j"]))) == len(ekf) == len(mcl) == 20
