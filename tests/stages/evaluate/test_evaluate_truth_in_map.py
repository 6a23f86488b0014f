"""truth_in_map: rigid fit of the map corners on the true ones (oracle: a known planar transform)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.common.geometry import fit_rigid_2d
from stages.evaluate.metrics import align_truth_to_map, transform_poses


def _transform(yaw_rad: float, t: np.ndarray):
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s], [s, c]]), np.asarray(t, float)


def test_fit_rigid_2d_recovers_a_known_transform_and_agrees_with_scipy():
    rng = np.random.default_rng(3)
    src = rng.uniform(-50, 50, (12, 2))
    R, t = _transform(np.deg2rad(0.7), [-0.2, 0.4])
    dst = src @ R.T + t + rng.normal(0, 0.01, src.shape)
    R_fit, t_fit = fit_rigid_2d(src, dst)
    assert np.degrees(np.arctan2(R_fit[1, 0], R_fit[0, 0])) == pytest.approx(0.7, abs=0.02)
    assert np.allclose(t_fit, t, atol=0.02)
    # independent: scipy's Kabsch on the centred 3D-lifted points
    lift = lambda p: np.column_stack([p - p.mean(0), np.zeros(len(p))])  # noqa: E731
    rot, _ = Rotation.align_vectors(lift(dst), lift(src))
    assert rot.as_euler("ZYX")[0] == pytest.approx(np.arctan2(R_fit[1, 0], R_fit[0, 0]), abs=1e-9)



def test_fit_rigid_2d_returns_a_rotation_for_mirrored_points():
    """A mirror is not a rigid motion: the fit stays a proper rotation (det +1), as the pose-graph bench's
    GNSS bound relies on."""
    src = np.random.default_rng(4).uniform(-500, 500, (400, 2))
    R_fit, _ = fit_rigid_2d(src, src * np.array([1.0, -1.0]))
    assert np.linalg.det(R_fit) == pytest.approx(1.0)

def test_align_truth_to_map_ignores_unmapped_true_corners_and_moves_poses():
    rng = np.random.default_rng(5)
    truth = rng.uniform(-100, 100, (30, 2))
    R, t = _transform(np.deg2rad(-0.3), [0.5, -0.3])
    mapped = truth[:8] @ R.T + t + rng.normal(0, 0.02, (8, 2))
    R_fit, t_fit, resid = align_truth_to_map(mapped, truth)
    assert len(resid) == 8 and resid.max() < 0.1
    q = np.array([[1.0, 2.0, 0.1], [-5.0, 3.0, 3.1]])
    moved = transform_poses(q, R_fit, t_fit)
    expected = transform_poses(q, R, t)
    assert np.allclose(moved[:, :2], expected[:, :2], atol=0.05)
    assert np.allclose(np.angle(np.exp(1j * (moved[:, 2] - expected[:, 2]))), 0.0, atol=np.deg2rad(0.05))


def test_align_truth_to_map_needs_three_matches():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    assert align_truth_to_map(truth[:2] + 0.1, truth) is None
    assert align_truth_to_map(truth + 5.0, truth) is None  # nothing within the coarse search's 4 m


def test_align_truth_to_map_finds_a_map_metres_off_a_consumer_receivers_frame():
    """A map 3.2 m and 0.5 deg off the true frame (a consumer receiver's bias): no map corner lies within the 1.5 m
    matching radius of its true corner, the coarse vote finds the shift and the fit recovers the transform."""
    rng = np.random.default_rng(12)
    truth = rng.uniform(-80, 80, (40, 2))
    R, t = _transform(np.deg2rad(0.5), [2.6, -1.8])
    mapped = truth[:25] @ R.T + t + rng.normal(0, 0.02, (25, 2))
    assert np.min(np.linalg.norm(mapped - truth[:25], axis=1)) > 1.5
    R_fit, t_fit, resid = align_truth_to_map(mapped, truth)
    assert len(resid) == 25 and resid.max() < 0.1
    assert np.degrees(np.arctan2(R_fit[1, 0], R_fit[0, 0])) == pytest.approx(0.5, abs=0.02)
    assert align_truth_to_map(mapped, truth, coarse_radius_m=0.0) is None  # the 1.5 m matching alone finds nothing


def test_align_truth_to_map_leaves_out_map_corners_that_are_no_true_corner():
    """40 map corners of a known transform (2 cm noise) and 6 decoys 1.2-1.45 m from a true corner (street furniture,
    a chamfer's other vertex): the fit recovers the transform as without the decoys and leaves them out."""
    rng = np.random.default_rng(9)
    truth = rng.uniform(-300, 300, (60, 2))
    R, t = _transform(np.deg2rad(0.2), [0.4, -0.7])
    mapped = truth[:40] @ R.T + t + rng.normal(0, 0.02, (40, 2))
    ang = rng.uniform(0, 2 * np.pi, 6)
    decoys = truth[40:46] @ R.T + t + rng.uniform(1.2, 1.45, (6, 1)) * np.column_stack([np.cos(ang), np.sin(ang)])
    R_fit, t_fit, resid = align_truth_to_map(np.vstack([mapped, decoys]), truth)
    R_ref, t_ref, _ = align_truth_to_map(mapped, truth)
    assert len(resid) == 40 and resid.max() < 0.1
    q = np.array([[150.0, -200.0, 0.3]])
    assert np.allclose(transform_poses(q, R_fit, t_fit)[:, :2], transform_poses(q, R_ref, t_ref)[:, :2], atol=1e-9)
    assert np.allclose(transform_poses(q, R_fit, t_fit)[:, :2], transform_poses(q, R, t)[:, :2], atol=0.02)


def test_align_truth_to_map_starts_from_the_corners_that_agree_not_from_decoys_at_the_matching_radius():
    """A tiny map: 5 map corners on true ones (2 cm noise) and 3 decoys 1.45-1.5 m from others, inside the 1.5 m
    matching radius (tiny seed 203's layout): the fit is the true transform and the decoys stay out."""
    truth = np.array([[-4.9, -10.3], [-32.4, -10.3], [10.0, 25.0], [40.0, -5.0], [-20.0, 35.0], [25.0, 45.0],
                      [-45.0, 20.0], [5.0, -40.0]])
    R, t = _transform(np.deg2rad(0.05), [0.3, -0.2])
    rng = np.random.default_rng(21)
    mapped = truth[:5] @ R.T + t + rng.normal(0, 0.02, (5, 2))
    decoys = truth[5:] @ R.T + t + np.array([[1.49, 0.0], [0.0, -1.47], [-1.05, 1.05]])
    R_fit, t_fit, resid = align_truth_to_map(np.vstack([mapped, decoys]), truth)
    assert len(resid) == 5 and resid.max() < 0.06
    assert np.degrees(np.arctan2(R_fit[1, 0], R_fit[0, 0])) == pytest.approx(0.05, abs=0.1)
