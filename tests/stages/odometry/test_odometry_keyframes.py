"""Keyframe pairs (scans metres apart): started from the prior trajectory, else a global registration (FPFH +
RANSAC), registered coarse to fine, gated with the pair's distance. The synthetic street of conftest.py raycast
from keyframes 3.5-7.5 m apart on a curving path, against the known poses."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.odometry.core import PriorPoses, Scan, estimate_edges, pair_scans
from stages.odometry.params import OdometryParams
from tests.stages.odometry.conftest import raycast_scan

T_VL = se3_from_xyz_rpy(0.0, 0.0, 1.9, 0.0, 0.0, 0.0)
SPACING_M = (5.5, 3.5, 7.5, 6.0, 4.0, 7.0, 5.0, 6.5, 4.5)


def _keyframes(scene, seed: int = 3):
    """A zig-zag down the street: the heading alternates between +-(10..20) deg, each step an arc (its chord at
    the mean of the two headings, as a car drives it)."""
    rng = np.random.default_rng(seed)
    x, y, last, poses = -40.0, 0.0, 0.0, []
    for k, step in enumerate((0.0,) + SPACING_M):
        yaw = (-1) ** k * np.radians(rng.uniform(10, 20))
        chord = 0.5 * (yaw + last) if k else yaw
        x, y, last = x + step * np.cos(chord), y + step * np.sin(chord), yaw
        poses.append(se3_from_xyz_rpy(x, y, 0.0, 0.0, 0.0, yaw))
    scans = [Scan(i, int(i * 1e9), raycast_scan(scene, T @ T_VL, rng), None) for i, T in enumerate(poses)]
    return poses, scans


def _errors(edges, poses):
    out = []
    for e in edges:
        true = se3_inverse(poses[e.scan_id - 1]) @ poses[e.scan_id]
        D = se3_inverse(true) @ e.T_prev_curr
        out.append((np.linalg.norm(D[:3, 3]), np.degrees(abs(np.arctan2(D[1, 0], D[0, 0])))))
    return np.array(out)


@pytest.fixture(scope="module")
def street_keyframes(street_scene):
    return _keyframes(street_scene)


def test_pairs_seconds_apart_are_keyframe_pairs_and_a_sweep_apart_are_not():
    cfg = OdometryParams()
    scans = [Scan(i, int(t * 1e9), np.zeros((0, 3)), None) for i, t in enumerate((0.0, 0.1, 0.2, 1.4, 1.5))]
    pairs = pair_scans(scans, {}, None, None, cfg)
    assert sorted(pairs.keyframe) == [3]


def test_keyframes_without_any_reference_start_from_a_global_registration(street_keyframes):
    poses, scans = street_keyframes
    cfg = OdometryParams(span_scans=[])
    edges = estimate_edges(list(scans), T_VL, {}, cfg)
    err = _errors(edges, poses)
    assert all(e.accepted for e in edges)
    assert err[:, 0].max() < 0.15 and err[:, 1].max() < 0.5, err
    # the same pairs as a dense drive's (constant velocity from the last pair, one-stage GICP) go wrong
    dense = OdometryParams(span_scans=[], keyframe={"min_dt_s": 10.0})
    err_dense = _errors(estimate_edges(list(scans), T_VL, {}, dense), poses)
    assert err_dense[:, 0].max() > 1.0, err_dense


def test_keyframes_start_from_the_prior_and_its_gate_rejects_a_prior_off_by_two_metres(street_keyframes):
    poses, scans = street_keyframes
    rng = np.random.default_rng(5)
    noisy = {i: T @ se3_from_xyz_rpy(*rng.normal(0, 0.03, 3), 0.0, 0.0, np.radians(rng.normal(0, 0.1)))
             for i, T in enumerate(poses)}
    cfg = OdometryParams(span_scans=[])
    prior = PriorPoses(noisy, sigma_m=0.05, sigma_rad=np.radians(0.2))
    edges = estimate_edges(list(scans), T_VL, {}, cfg, prior=prior)
    err = _errors(edges, poses)
    assert all(e.accepted for e in edges) and err[:, 0].max() < 0.15, err
    # the registration's information is floored at the keyframe error per metre (0.015 m/m): never claims mm
    for e in edges:
        cov = np.linalg.inv(e.information)
        d = np.linalg.norm(e.T_prev_curr[:3, 3])
        assert np.sqrt(cov[3, 3]) >= 0.015 * d * 0.99
    bad = dict(noisy)
    bad[5] = noisy[5] @ se3_from_xyz_rpy(2.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # the prior's pose 5 two metres off
    edges = estimate_edges(list(scans), T_VL, {}, cfg, prior=PriorPoses(bad, 0.05, np.radians(0.2)))
    verdict = {e.scan_id: e.accepted for e in edges}
    assert verdict[5] is False and verdict[6] is False  # both increments touching pose 5 disagree with the scans
    assert sum(verdict.values()) == len(edges) - 2


@pytest.mark.parametrize("dx, dy, yaw_deg, plausible", [
    (6.0, 0.0, 0.0, True), (5.4, 1.3, 26.6, True),  # straight; a turn: the chord at half the turn
    (-6.0, 0.0, 0.0, True), (-5.4, -1.3, 26.6, True),  # reversing
    (6.0, 3.0, 0.0, False), (-20.5, -9.7, 7.7, False),  # sideways; a match to a repeated facade (tiny seed 861)
    (0.3, 0.6, 0.0, True),  # under 1 m: not judged
])
def test_a_keyframe_pair_must_move_along_its_heading(dx, dy, yaw_deg, plausible):
    from stages.odometry.keyframes import plausible_motion

    T = se3_from_xyz_rpy(dx, dy, 0.0, 0.0, 0.0, np.radians(yaw_deg))
    assert plausible_motion(T, np.radians(15.0)) is plausible
