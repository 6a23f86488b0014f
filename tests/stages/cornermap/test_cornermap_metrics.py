"""The bench's scorer on hand-made maps with known precision, recall and errors."""
from __future__ import annotations

import numpy as np

from stages.cornermap.metrics import local_frame_offset, score_corner_map


def test_scores_of_a_known_map():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    truth_theta = np.tile([0.0, np.pi / 2], (4, 1))
    map_en = np.array([[0.03, 0.04], [10.0, 0.0], [50.0, 0.0]])  # 0.05 m error, exact, a false positive
    map_theta = np.array([[np.radians(2.0), np.pi / 2], [np.pi / 2, 0.0], [0.0, 1.0]])  # 2 deg, swapped pair
    eligible = np.array([True, True, True, False])
    s = score_corner_map(map_en, map_theta, truth, truth_theta, eligible)
    assert s["precision"] == 2 / 3 and s["recall"] == 2 / 3 and s["n_duplicates"] == 0
    np.testing.assert_allclose(s["rms_pos_m"], np.sqrt(0.05**2 / 2))
    np.testing.assert_allclose(s["rms_angle_deg"], np.sqrt(2.0**2 / 2))


def test_local_offset_averages_nearby_poses_only():
    pose_true = np.column_stack([np.arange(0.0, 200.0, 1.0), np.zeros(200)])
    pose_opt = pose_true + np.where(pose_true[:, :1] < 100.0, [0.2, -0.1], [0.0, 0.3])
    off = local_frame_offset(np.array([[20.0, 5.0], [180.0, 5.0], [1000.0, 0.0]]), pose_true, pose_opt, 50.0)
    np.testing.assert_allclose(off, [[0.2, -0.1], [0.0, 0.3], [0.0, 0.0]])


def test_co_located_true_corners_match_by_walls():
    truth = np.array([[0.0, 0.0], [0.0, 0.0]])  # two touching buildings share a vertex
    truth_theta = np.array([[0.0, np.pi / 2], [np.pi / 2, np.pi]])
    map_theta = np.array([[np.pi / 2, np.pi], [0.0, np.pi / 2]])
    s = score_corner_map(np.zeros((2, 2)), map_theta, truth, truth_theta, np.ones(2, bool))
    assert s["recall"] == 1.0 and s["n_duplicates"] == 0 and s["rms_angle_deg"] < 1e-9
