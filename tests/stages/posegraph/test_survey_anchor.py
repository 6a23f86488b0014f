"""Survey anchors: the vertical part of a ground registration, horizontal anchors from marking matches, and
their effect on a biased-GNSS graph (synthetic truth)."""
from __future__ import annotations

import numpy as np

from stages.common.geometry import se3_from_xyz_rpy
from stages.common.trajectory_metrics import horizontal_errors_m, rms
from stages.posegraph.anchors.marking_match import MarkingMatch
from stages.posegraph.anchors.survey_anchor import (
    SurveyMatch,
    anchor_scan,
    build_survey_index,
    rematched_vertical,
    survey_priors,
    vertical_information,
    vertical_part,
)
from stages.posegraph.anchors.survey_markings import horizontal_information_body, submap_scan_indices
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.graph import optimize
from tests.stages.posegraph.conftest import posegraph_config


def test_vertical_part_keeps_the_horizontal_position_and_takes_height_and_tilt():
    T_init = se3_from_xyz_rpy(100.0, 50.0, 1.0, 0.0, 0.0, 0.7)
    T_reg = se3_from_xyz_rpy(102.5, 48.0, 1.2, 0.01, -0.02, 0.75)  # slid 3 m along the road, other heading
    T = vertical_part(T_reg, T_init)
    assert np.linalg.norm(T[:2, 3] - T_init[:2, 3]) < 0.01
    assert abs(T[2, 3] - 1.2) < 0.08  # onto the registered ground plane (tilted by 0.02 rad over 3 m)
    assert np.allclose(T[:3, 2], T_reg[:3, 2], atol=1e-9)  # registered up axis
    yaw = np.arctan2(T[1, 0], T[0, 0])
    assert abs(yaw - 0.7) < 1e-3  # heading kept


def test_horizontal_information_is_the_enu_block_seen_in_the_body_frame():
    R = se3_from_xyz_rpy(0, 0, 0, 0.0, 0.0, np.pi / 2)[:3, :3]  # vehicle x points north
    info_en = np.diag([1 / 0.5 ** 2, 1 / 0.03 ** 2])  # east weak, north strong
    body = horizontal_information_body(info_en, R)
    assert np.allclose(body[:3, :], 0) and np.allclose(body[:, :3], 0)
    assert np.isclose(body[3, 3], 1 / 0.03 ** 2) and np.isclose(body[4, 4], 1 / 0.5 ** 2)  # body x = north


def _match(accepted: bool, shift=(0.3, -0.2)) -> MarkingMatch:
    info = np.diag([400.0, 900.0]) if accepted else np.zeros((2, 2))
    return MarkingMatch(np.array(shift), info, 0.8, 1000, accepted, "accepted" if accepted else "score")


def test_survey_priors_combine_vertical_and_horizontal_parts_where_each_was_accepted():
    T = se3_from_xyz_rpy(10, 20, 1, 0, 0, 0.3)
    vinfo = vertical_information(0.02, 0.001)
    both = SurveyMatch(0, T, vinfo, 0.9, 0.1, True, "accepted", _match(True))
    only_h = SurveyMatch(1, T, vinfo, 0.1, 0.3, False, "fitness", _match(True))
    only_v = SurveyMatch(2, T, vinfo, 0.9, 0.1, True, "accepted", _match(False))
    none = SurveyMatch(3, T, vinfo, 0.1, 0.3, False, "fitness", _match(False))
    priors = {pr.i: pr for pr in survey_priors([both, only_h, only_v, none])}
    assert sorted(priors) == [0, 1, 2]
    assert np.allclose(priors[0].T_map_vehicle[:2, 3], [10.3, 19.8])
    assert priors[0].information[5, 5] > 1e3 and priors[0].information[3, 3] > 100
    assert priors[1].information[5, 5] == 0 and priors[1].information[3, 3] > 100
    assert np.allclose(priors[2].T_map_vehicle[:2, 3], [10, 20]) and priors[2].information[3, 3] < 1e-6


def test_submap_indices_follow_travel_and_the_scan_cap():
    pos = np.column_stack([np.r_[np.zeros(20), np.arange(1, 61) * 0.9], np.zeros(80), np.zeros(80)])
    ks = submap_scan_indices(pos, 40, half_travel_m=8.0, max_scans=10)
    assert ks[0] == 32 and ks[-1] == 48  # 0.9 m steps: 8 each side within 8 m of travel (cap 10 not reached)
    ks = submap_scan_indices(pos, 22, half_travel_m=8.0, max_scans=10)
    assert ks[0] == 12  # standing still: the cap, not the travel, limits the scans before


def test_submap_scan_step_thins_the_window_on_the_drive_grid():
    """With a step the window is the same, its scans every step-th of the drive (so keyframes and rounds share
    them) plus the keyframe's own."""
    pos = np.column_stack([np.arange(80) * 0.5, np.zeros(80), np.zeros(80)])
    full = submap_scan_indices(pos, 41, half_travel_m=8.0, max_scans=10)
    assert full.tolist() == list(range(31, 52))
    ks = submap_scan_indices(pos, 41, half_travel_m=8.0, max_scans=10, step=2)
    assert ks.tolist() == [32, 34, 36, 38, 40, 41, 42, 44, 46, 48, 50]
    assert set(submap_scan_indices(pos, 43, 8.0, 10, step=2)) - {43} <= set(range(0, 80, 2))


def test_horizontal_anchors_pull_a_gnss_biased_graph_onto_truth(two_lap_drive):
    """Biased GNSS (0.85 m) alone leaves the graph decimetres off; horizontal anchors at truth every 10 poses
    with 3 cm sigma (what an accepted marking match gives) bring it within 5 cm."""
    T_true, drive = two_lap_drive
    cfg = posegraph_config()
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss)
    before = rms(horizontal_errors_m(optimize(problem), T_true))
    anchors = [SurveyMatch(i, T_true[i], np.zeros((6, 6)), 0.0, 0.0, False, "no ground",
                           MarkingMatch(np.zeros(2), np.eye(2) / 0.03 ** 2, 0.8, 1000, True, "accepted"))
               for i in range(0, len(T_true), 10)]
    problem.pose_priors += survey_priors(anchors)
    after = rms(horizontal_errors_m(optimize(problem), T_true))
    assert before > 0.15, before
    assert after < 0.05, (before, after)


def test_matched_heading_becomes_a_yaw_prior_only_when_asked():
    from dataclasses import replace

    T = se3_from_xyz_rpy(10, 20, 1, 0, 0, 0.3)
    h = replace(_match(True), yaw_rad=np.deg2rad(-0.4))
    m = SurveyMatch(0, T, vertical_information(0.02, 0.001), 0.9, 0.1, True, "accepted", h)
    plain = survey_priors([m])[0]
    with_yaw = survey_priors([m], yaw_sigma_rad=np.deg2rad(0.2))[0]
    def yaw(R):
        return np.arctan2(R[1, 0], R[0, 0])

    assert np.isclose(yaw(plain.T_map_vehicle), 0.3) and np.isclose(plain.information[2, 2], 0.0)
    assert np.isclose(yaw(with_yaw.T_map_vehicle), 0.3 - np.deg2rad(0.4))
    assert np.allclose(with_yaw.T_map_vehicle[:3, 3], plain.T_map_vehicle[:3, 3])  # position unchanged
    assert np.isclose(with_yaw.information[2, 2], np.deg2rad(0.2) ** -2)  # level vehicle: body z = map up


def test_anchoring_rounds_match_again_from_the_anchored_estimate(two_lap_drive):
    """Matches that keep 40 % of the error of the estimate they start from (a submap placed with a wrong heading
    matches short of the truth): one round leaves the graph that share off; rounds re-matched from the anchored
    estimate converge onto the truth, and stop once a round moves no pose more than the tolerances."""
    from stages.posegraph.solve import anchored

    T_true, drive = two_lap_drive
    keep = 0.4

    def callback(poses, offsets):
        matches = []
        for i in range(0, len(T_true), 10):
            shift = (1 - keep) * (T_true[i, :2, 3] - poses[i, :2, 3])
            matches.append(SurveyMatch(i, poses[i], np.zeros((6, 6)), 0.0, 0.0, False, "no ground",
                                       MarkingMatch(shift, np.eye(2) / 0.03 ** 2, 0.8, 1000, True, "accepted")))
        return survey_priors(matches)

    errors, records = {}, {}
    for n_rounds in (1, 4):
        cfg = posegraph_config({"anchors.rounds": n_rounds, "anchors.round_tol_m": 0.09, "anchors.round_tol_deg": 0.5})
        problem, offsets = base_problem([drive], cfg.factors, cfg.gnss)
        start = optimize(problem)
        rounds: list[dict] = []
        poses = anchored(problem, start, offsets, callback, cfg.anchors, rounds,
                         lambda initial, problem=problem: optimize(problem, initial=initial))
        errors[n_rounds], records[n_rounds] = rms(horizontal_errors_m(poses, T_true)), rounds
        assert len(problem.pose_priors) == len(range(0, len(T_true), 10)) + len(
            base_problem([drive], cfg.factors, cfg.gnss)[0].pose_priors)  # a round replaces the previous anchors
    before = rms(horizontal_errors_m(start, T_true))
    assert before > 0.15, before
    assert errors[1] > 0.25 * before, (before, errors)
    assert errors[4] < 0.05 and errors[4] < 0.4 * errors[1], (before, errors)
    moved = [r["max_moved_m"] for r in records[4]]
    assert len(records[1]) == 1 and moved == sorted(moved, reverse=True), records
    assert len(moved) < 4 and moved[-1] <= 0.09 < moved[-2], moved  # stopped by the tolerance, not the cap


def _ground_m(e: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A sloped street (2 % east, 1 % north, a 3 cm crown across) with 15 cm kerbs at |north| > 6 m."""
    return 0.02 * e + 0.01 * n - 0.03 * (n / 6.0) ** 2 + 0.15 * (np.abs(n) > 6.0)


def test_a_ground_match_carried_to_a_moved_estimate_equals_matching_again():
    """The vertical anchor of a keyframe whose estimate moved 0.7 m (an anchoring round) is the previous round's
    registered ground under the new estimate: height within 5 mm and tilt within the anchor's stated std of a
    fresh registration from there, and within 1 cm / 0.05 deg of the truth. An estimate moved beyond the tolerance
    is matched again."""
    cfg = posegraph_config().anchors.ground
    rng = np.random.default_rng(4)
    e, n = np.meshgrid(np.arange(-60, 60, 0.1), np.arange(-20, 20, 0.1))
    survey = np.column_stack([e.ravel(), n.ravel(), _ground_m(e.ravel(), n.ravel())])
    pts, tree = build_survey_index(survey, cfg.voxel_m)
    T_true = se3_from_xyz_rpy(3.0, 1.0, float(_ground_m(np.array(3.0), np.array(1.0))), 0.0, 0.0, 0.2)
    up = np.array([-0.02, -0.01 + 0.06 * 1.0 / 36.0, 1.0])  # the street's normal under the vehicle
    up /= np.linalg.norm(up)
    x = np.array([np.cos(0.2), np.sin(0.2), 0.0])
    x -= up * (x @ up)
    x /= np.linalg.norm(x)
    T_true[:3, :3] = np.column_stack([x, np.cross(up, x), up])  # standing on the slope, heading 0.2 rad
    near = survey[np.hypot(survey[:, 0] - 3.0, survey[:, 1] - 1.0) < 25.0]
    near = near[::3] + rng.normal(0, 0.01, near[::3].shape)
    scan = (near - T_true[:3, 3]) @ T_true[:3, :3]  # the vehicle's view of the ground
    T_a = T_true.copy()
    T_a[:3, 3] += [0.4, -0.3, 0.1]
    T_b = T_true.copy()
    T_b[:3, 3] += [-0.1, 0.2, -0.05]  # the next round's estimate: 0.71 m from T_a
    first = anchor_scan(0, scan, T_a, pts, tree, cfg)
    fresh = anchor_scan(0, scan, T_b, pts, tree, cfg)
    carried = rematched_vertical(first, T_b, max_shift_m=1.0)
    assert first.accepted and fresh.accepted and carried is not None and carried.accepted
    tilt_deg = lambda A, B: np.rad2deg(np.arccos(np.clip(A[:3, 2] @ B[:3, 2], -1, 1)))  # noqa: E731
    assert abs(carried.T_map_vehicle[2, 3] - fresh.T_map_vehicle[2, 3]) < 0.005
    # each registration measures the ground under its own start (the horizontal position is held): on this crowned
    # street the two starts, 0.71 m apart, see planes up to ~0.05 deg apart, within the anchor's stated std
    assert tilt_deg(carried.T_map_vehicle, fresh.T_map_vehicle) < np.rad2deg(cfg.min_sigma_rad)
    np.testing.assert_allclose(carried.T_map_vehicle[:2, 3], fresh.T_map_vehicle[:2, 3], atol=1e-3)  # T_b's, slid
    assert np.linalg.norm(carried.T_map_vehicle[:2, 3] - T_b[:2, 3]) < 0.005  # along the up axis onto the ground
    assert abs(carried.T_map_vehicle[2, 3] - _ground_m(T_b[0, 3], T_b[1, 3])) < 0.01
    assert tilt_deg(carried.T_map_vehicle, T_true) < 0.05
    assert rematched_vertical(first, T_b, max_shift_m=0.5) is None  # moved 0.71 m: match again
    T_mid, T_c = T_a.copy(), T_a.copy()
    T_mid[0, 3] += 0.6
    T_c[0, 3] += 1.2  # carried twice, 0.6 m each time: 1.2 m from where it was registered
    assert rematched_vertical(first, T_mid, 1.0) is not None
    assert rematched_vertical(rematched_vertical(first, T_mid, 1.0), T_c, 1.0) is None
    from dataclasses import replace

    rejected = replace(first, accepted=False, reason="fitness 0.31 < 0.50")  # its start failed the gates
    assert rematched_vertical(rejected, T_b, max_shift_m=1.0) is None  # matched again from the new estimate


def test_the_worker_initializer_shares_the_downsampled_survey_and_its_normals_through_the_cache_dir(tmp_path):
    """Two processes' ground-anchor state from one survey source with a ``cache_dir``: the second reads no survey
    and gets the first's arrays, which equal the unshared ones (``build_survey_index``, ``survey_plane_normals``)."""
    from pipeline.parallel import worker_state
    from stages.posegraph.anchors.survey_anchor import (
        SurveyArrays,
        _use_survey_and_drives,
        survey_plane_normals,
    )

    rng = np.random.default_rng(5)
    survey = np.column_stack([rng.uniform(0, 40, 20000), rng.uniform(0, 40, 20000), rng.normal(0, 0.02, 20000)])
    source = SurveyArrays(survey)
    source.cache_dir = tmp_path
    reads = []
    real_read = source.read
    source.read = lambda: reads.append(1) or real_read()
    states = []
    for _ in range(2):  # as two processes: worker_cache keeps nothing outside a shared pool
        _use_survey_and_drives(source, 0.2, [], None, True)
        states.append(dict(worker_state()))
    assert len(reads) == 1
    pts, tree = build_survey_index(survey, 0.2)
    for st in states:
        np.testing.assert_array_equal(st["survey_pts"], pts)
        np.testing.assert_array_equal(st["survey_tree"].data, tree.data)
        np.testing.assert_array_equal(st["survey_normals"], survey_plane_normals(pts))
