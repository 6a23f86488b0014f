"""The incremental solve's window (stages/posegraph/window.py) on a synthetic truth: a held map whose frame is off by
a known offset, with a far part the new drive never reaches; a new pass beside it with absolute evidence (position
fixes) and loops onto the map. Oracles: the window's poses move toward the truth, to within the covariance the solve
states; the far poses keep their published values; the frame test fires on an offset far beyond the map's stated
frame covariance and not on one within it."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from stages.posegraph.factors.graph import Between, PositionPrior, Problem, optimize
from stages.posegraph.window import (
    FramePrior,
    add_window,
    anchor_marginal,
    correct_window,
    frame_test,
    log_pose,
    select_window,
    taper_weights,
)
from tests.stages.posegraph.test_regions import _block, _exp

FAR_M = 2000.0


def _night(offset_en_m, prior_std_m: float, seed: int = 7):
    """Held map: a 240-pose block (near) and the same block FAR_M east (far), published with the near and far parts
    shifted by ``offset_en_m`` (the map's frame error) and 3 mm of relative noise; the new pass 0.3 m beside the near
    block with fixes every 2 poses (0.05 m) and loops every 4 poses onto the map. Returns the solved night."""
    rng = np.random.default_rng(seed)
    near = np.array(_block(60, 1.0, 0.0))
    far = near.copy()
    far[:, 0, 3] += FAR_M
    truth_held = np.concatenate([near, far])
    held = truth_held.copy()
    held[:, :2, 3] += np.asarray(offset_en_m, float) + rng.normal(0, 0.003, (len(held), 2))
    held_cov = np.tile(np.diag([0.003 ** 2, 0.003 ** 2, 1e-4 ** 2]).reshape(9), (len(held), 1))
    drive_of_row = np.repeat([0, 1], len(near))
    truth_new = near.copy()
    truth_new[:, 1, 3] += 0.3
    n = len(truth_new)
    p = Problem(n, truth_new.copy())
    p.initial[:, :2, 3] += np.asarray(offset_en_m, float)  # the new pass starts on the map (its loops' view)
    for i in range(n - 1):
        rel = np.linalg.inv(truth_new[i]) @ truth_new[i + 1] @ _exp(rng.normal(0, 0.002, 6))
        p.betweens.append(Between(i, i + 1, rel, np.diag([1e5] * 3 + [1e4] * 3)))
    for i in range(0, n, 2):
        p.positions.append(PositionPrior(i, truth_new[i, :3, 3] + rng.normal(0, 0.05, 3), np.full(3, 0.05), "none"))
    reached = list(range(0, len(near), 4))
    held_of = {n + m: g for m, g in enumerate(reached)}
    p.n_poses = n + len(reached)
    p.initial = np.concatenate([p.initial, held[reached]])
    for m, g in enumerate(reached):
        rel = np.linalg.inv(truth_held[g]) @ truth_new[g] @ _exp(np.r_[rng.normal(0, 0.001, 3),
                                                                      rng.normal(0, 0.01, 3)])
        p.betweens.append(Between(n + m, g, rel, np.diag([0.002 ** -2] * 3 + [0.02 ** -2] * 3), "loop"))
    prior = FramePrior(held[:len(near), :2, 3].mean(0), np.diag([prior_std_m ** 2] * 2 + [1e-3 ** 2]), prior_std_m,
                       "map_frame")
    rows, left_out = select_window(held[:, :2, 3], p.initial[:n, :2, 3], 12.0, 8 * n)
    win = add_window(p, held_of, held, held_cov, rows, left_out, prior)
    poses = optimize(p)
    cov_post = anchor_marginal(p, poses, win.anchor)
    corrected = correct_window(held, win, poses[win.anchor], drive_of_row)
    test = frame_test(log_pose(np.linalg.inv(win.A_pub) @ poses[win.anchor]), win.cov_prior, cov_post)
    return held, truth_held, corrected, win, cov_post, test, len(near)


def test_the_window_moves_the_overlapping_map_to_the_truth_within_its_stated_covariance():
    offset = np.array([0.25, -0.15])
    held, truth, corrected, win, cov_post, test, n_near = _night(offset, prior_std_m=0.2)
    assert set(win.rows.tolist()) == set(range(n_near))  # the near block, nothing of the far one
    before = held[:n_near, :2, 3] - truth[:n_near, :2, 3]
    after = corrected[:n_near, :2, 3] - truth[:n_near, :2, 3]
    assert np.linalg.norm(before.mean(0)) > 0.25
    assert np.linalg.norm(after.mean(0)) < 0.1 * np.linalg.norm(before.mean(0))
    # the map's remaining common error is within what the solve states for the frame (2 dof, 99.9 %)
    e = after.mean(0)
    P = cov_post[3:5, 3:5] + np.eye(2) * 0.003 ** 2 / n_near  # + the mean of the poses' relative noise
    assert e @ np.linalg.solve(P, e) < chi2.ppf(0.999, 2)
    # far poses: bit for bit as published
    assert np.array_equal(corrected[n_near:], held[n_near:])
    # the map's shape is kept: the correction is rigid (relative geometry within the 3 mm noise)
    d_before = np.diff(held[:n_near, :2, 3], axis=0)
    d_after = np.diff(corrected[:n_near, :2, 3], axis=0)
    assert np.max(np.abs(d_after - d_before)) < 1e-3
    # a 1.5 sigma offset of a map that states its frame honestly: consistent
    assert test["dof"] >= 2 and not test["advised"]


def test_the_frame_test_fires_on_an_offset_beyond_the_stated_frame_covariance():
    test = _night(np.array([0.6, 0.4]), prior_std_m=0.05)[5]
    assert test["dof"] >= 2 and test["advised"] and test["chi2"] > test["threshold"]


def test_a_consistent_map_is_not_flagged():
    test = _night(np.array([0.0, 0.0]), prior_std_m=0.05)[5]
    assert test["dof"] >= 2 and not test["advised"]


def test_the_correction_ramps_in_where_a_window_run_meets_held_poses_outside_it():
    T = np.array(_block(60, 1.0, 0.0))  # 1 m per pose
    drive_of_row = np.zeros(len(T), int)
    rows = np.arange(50, 150)  # window in the middle of one drive: both ends border poses outside it
    w = taper_weights(T, rows, drive_of_row, taper_m=20.0)
    assert w[0] == w[-1] == 0.05 and np.all(w[25:75] == 1.0)
    assert np.all(np.diff(w[:20]) > 0) and np.all(np.diff(w[-20:]) < 0)
    # a run that ends at the drive's end (or at another drive) has nothing to meet there
    w_end = taper_weights(T, np.arange(140, len(T)), drive_of_row, taper_m=20.0)
    assert w_end[-1] == 1.0 and w_end[0] == 0.05


def test_the_window_is_capped_nearest_first():
    held_xy = np.column_stack([np.arange(100.0), np.zeros(100)])
    new_xy = np.array([[0.0, 1.0]])
    rows, left_out = select_window(held_xy, new_xy, 12.0, 5)
    assert rows.tolist() == [0, 1, 2, 3, 4] and left_out == 12 - 5


def test_maps_show_prints_the_frame_test():
    from mapservice.maps_show import drift_lines

    frame = {"shift_en_m": [0.12, -0.03], "rotation_deg": 0.01, "chi2": 40.0, "dof": 3, "threshold": 16.27,
             "advised": True, "window_poses": 250}
    lines = drift_lines({"version": "v0003", "regions": [], "frame": frame, "advised": ["frame"]})
    assert lines[0].startswith("reoptimize advised: the held map's frame moved (+0.120, -0.030) m")
    ok = drift_lines({"version": "v0003", "regions": [], "frame": frame | {"chi2": 2.0, "advised": False}})
    assert ok[0].startswith("drift: frame consistent") and "2.0 of threshold 16.3" in ok[0]


def test_the_frame_prior_moves_with_its_reference_point_and_is_never_singular():
    from stages.posegraph.window import frame_prior_at

    prior = FramePrior(np.zeros(2), np.diag([0.01, 0.04, 1e-4]), 0.1, "map_frame")
    c = frame_prior_at(prior, np.array([100.0, 0.0]))  # 100 m east: a rotation moves the point north
    assert np.isclose(c[3, 3], 0.01) and np.isclose(c[4, 4], 0.04 + 1e-4 * 100.0 ** 2)
    assert np.isclose(c[4, 2], 1e-4 * 100.0)
    flat = frame_prior_at(FramePrior(np.zeros(2), np.zeros((3, 3)), 0.0, "map_frame"), np.ones(2))
    assert np.linalg.eigvalsh(flat).min() > 0
