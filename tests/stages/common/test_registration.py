"""Oracles for the shared registration core: known motions on a raycast street, information frames."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.registration import (
    adjoint_se3,
    floor_information,
    plane_hessian,
    point_to_plane_hessian,
    prepare_cloud,
    register_clouds,
    regularize_covariances,
    voxel_downsample,
)
from tests.stages.odometry.conftest import build_street_scene, raycast_scan


@pytest.fixture(scope="module")
def street_scene():
    return build_street_scene(seed=7)


def _pose_error(T_est, T_true):
    D = se3_inverse(T_true) @ T_est
    return np.linalg.norm(D[:3, 3]), np.rad2deg(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec()))


@pytest.mark.parametrize("method,tol_m,tol_deg", [("gicp", 0.01, 0.05), ("point_to_plane", 0.04, 0.1)])
def test_register_recovers_known_motion_within_mm(street_scene, method, tol_m, tol_deg):
    """GICP recovers a 1.2 m / 1.7 deg motion within 1 cm; point-to-plane is measurably worse on sparse
    32-beam rings (ground normals from collinear ring neighbours), which is why GICP is the default."""
    rng = np.random.default_rng(1)
    T_w_prev = se3_from_xyz_rpy(0, 0, 1.8, 0, 0, 0.0)
    T_prev_curr = se3_from_xyz_rpy(1.2, 0.15, 0.02, 0.004, -0.003, 0.03)
    T_w_curr = T_w_prev @ T_prev_curr
    prev = prepare_cloud(raycast_scan(street_scene, T_w_prev, rng, noise_m=0.005), 0.3)
    curr = prepare_cloud(raycast_scan(street_scene, T_w_curr, rng, noise_m=0.005), 0.3)
    T_init = T_prev_curr @ se3_from_xyz_rpy(0.3, -0.2, 0.05, 0.0, 0.0, 0.02)  # an INS-grade guess
    res = register_clouds(curr, prev, T_init, method=method, max_corr_m=1.5, max_iterations=60)
    dt_m, dr_deg = _pose_error(res.T_target_source, T_prev_curr)
    assert res.converged and res.fitness > 0.8
    assert dt_m < tol_m and dr_deg < tol_deg, (dt_m, dr_deg)
    assert np.all(np.linalg.eigvalsh(res.information) > 0)
    # the Hessian from open3d's correspondence set equals a fresh nearest-neighbour search (scipy) at that pose
    H_search = point_to_plane_hessian(curr, prev, res.T_target_source, 1.5, 0.05)
    np.testing.assert_allclose(res.hessian, H_search, rtol=1e-9, atol=1e-9 * np.abs(H_search).max())
    np.testing.assert_allclose(res.information, floor_information(H_search, 0.005, 0.0002), rtol=1e-9)


def test_plane_hessian_equals_the_estimated_normals_on_an_exact_plane_and_holds_no_in_plane_information():
    """On a noise-free tilted plane the neighbours' normals are the plane's: ``plane_hessian`` equals
    ``point_to_plane_hessian`` there; only the height and the two tilts are constrained (target frame at T = I:
    no information along the plane or about its normal); a source point with no target point within max_corr_m
    adds nothing."""
    rng = np.random.default_rng(3)
    R = Rotation.from_rotvec([0.02, -0.03, 0.0]).as_matrix()
    n = R[:, 2]

    def on_plane(k, half_m):
        uv = rng.uniform(-half_m, half_m, (k, 2))
        return uv @ R[:, :2].T + 0.4 * R[:, :2].sum(axis=1) - 1.8 * n

    tgt_m, src_m = on_plane(3000, 15.0), on_plane(800, 14.0)
    T = se3_from_xyz_rpy(0.8, 0.1, 0.0, 0.0, 0.0, 0.01)
    src_moved_back = (src_m - T[:3, 3]) @ T[:3, :3]  # source points in the source frame: T maps them onto tgt's
    H_plane = plane_hessian(src_moved_back, tgt_m, n, T, 1.0, 0.05)
    H_knn = point_to_plane_hessian(prepare_cloud(src_moved_back, 0.0, with_covariances=False),
                                   prepare_cloud(tgt_m, 0.0, with_covariances=False), T, 1.0, 0.05)
    np.testing.assert_allclose(H_plane, H_knn, rtol=1e-6, atol=1e-6 * np.abs(H_knn).max())
    H0 = plane_hessian(tgt_m, tgt_m, n, np.eye(4), 1.0, 0.05)
    scale = np.abs(H0).max()
    for xi in (np.r_[n, 0, 0, 0], np.r_[0, 0, 0, R[:, 0]], np.r_[0, 0, 0, R[:, 1]]):
        assert np.linalg.norm(H0 @ xi) < 1e-9 * scale
    assert np.linalg.matrix_rank(H0, tol=1e-9 * scale) == 3
    far = np.vstack([tgt_m[:10], tgt_m[:10] + 40.0 * R[:, 0]])  # 10 points on the target, 10 far beyond its edge
    np.testing.assert_allclose(plane_hessian(far, tgt_m, n, np.eye(4), 1.0, 0.05),
                               plane_hessian(far[:10], tgt_m, n, np.eye(4), 1.0, 0.05), rtol=1e-12)
    assert not plane_hessian(np.zeros((0, 3)), tgt_m, n, np.eye(4), 1.0, 0.05).any()


def test_voxel_downsample_keeps_each_occupied_voxels_mean_point():
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.2, 0.2], [3.0, 0.0, 0.0], [3.2, 0.2, 0.2]], np.float32)  # two voxels
    got = voxel_downsample(pts, 1.0)
    assert got.dtype == np.float64
    np.testing.assert_allclose(got[np.argsort(got[:, 0])], [[0.1, 0.1, 0.1], [3.1, 0.1, 0.1]], atol=1e-6)
    np.testing.assert_array_equal(voxel_downsample(pts, 0.0), pts.astype(np.float64))  # no voxel: unchanged
    assert voxel_downsample(np.zeros((0, 3)), 1.0).shape == (0, 3)


def test_information_body_frame_matches_gtsam_adjoint():
    T = se3_from_xyz_rpy(3.0, -1.0, 0.5, 0.1, -0.2, 0.7)
    Ad_gtsam = gtsam.Pose3(T).AdjointMap()
    np.testing.assert_allclose(adjoint_se3(T), Ad_gtsam, atol=1e-12)


def test_floor_information_caps_confidence():
    H = np.diag([1e12] * 6)
    cov = np.linalg.inv(floor_information(H, 0.01, 0.001))
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [0.001] * 3 + [0.01] * 3, rtol=1e-3)


def _exact_plane_street(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """Two walls, an end wall and a flat layer of points at one height (what a ring at 0 deg elevation gives
    when range noise lies along the ray): every neighbourhood is exactly planar."""
    t = rng.uniform(-20, 20, n)
    walls = [np.column_stack([t, np.full(n, y), rng.uniform(-1.5, 8, n)]) for y in (6.0, -7.0)]
    layer = np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), np.zeros(n)])
    end = np.column_stack([np.full(n, 25.0), rng.uniform(-7, 6, n), rng.uniform(-1.5, 8, n)])
    return np.vstack([*walls, layer[np.abs(layer[:, 1]) > 8], end])


def test_gicp_on_exactly_planar_neighbourhoods_needs_regularised_covariances():
    """Raw covariances of exact planes are singular; GICP then diverges (NaN, reported not converged).
    With the (1 mm)^2 eigenvalue floor it recovers the motion to 1 mm."""
    pts = _exact_plane_street(np.random.default_rng(3))
    T = se3_from_xyz_rpy(0.4, 0.03, 0.0, 0.0, 0.0, np.radians(0.5))
    src = (pts - T[:3, 3]) @ T[:3, :3]
    raw = register_clouds(prepare_cloud(src, 0.5, 20, min_cov_eigenvalue_m2=0.0),
                          prepare_cloud(pts, 0.5, 20, min_cov_eigenvalue_m2=0.0), np.eye(4), max_corr_m=1.0)
    assert not raw.converged
    raw_cov = np.asarray(prepare_cloud(pts, 0.5, 20, min_cov_eigenvalue_m2=0.0).covariances)
    floored_cov = np.asarray(prepare_cloud(pts, 0.5, 20).covariances)  # written into open3d's buffer in place
    np.testing.assert_allclose(floored_cov - raw_cov, np.broadcast_to(1e-6 * np.eye(3), raw_cov.shape), atol=1e-12)
    fixed = register_clouds(prepare_cloud(src, 0.5, 20), prepare_cloud(pts, 0.5, 20), np.eye(4), max_corr_m=1.0)
    dt_m, dr_deg = _pose_error(fixed.T_target_source, T)
    assert fixed.converged and dt_m < 1e-3 and dr_deg < 0.01, (dt_m, dr_deg)


def test_regularize_covariances_floors_eigenvalues_and_keeps_eigenvectors():
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=1).as_matrix()
    w = np.column_stack([np.zeros(50), rng.uniform(1e-4, 1e-2, 50), rng.uniform(0.1, 1.0, 50)])
    C = np.einsum("nij,nj,nkj->nik", R, w, R)
    out = regularize_covariances(C, 1e-6)
    w_out, V_out = np.linalg.eigh(out)
    np.testing.assert_allclose(w_out, np.sort(w + 1e-6, axis=1), rtol=1e-6, atol=1e-12)
    # the smallest axis stays the plane normal
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", V_out[:, :, 0], R[:, :, 0])), 1.0, atol=1e-6)


def _open3d_threads_after_a_registration(_x=None) -> tuple[int, int | None]:
    import open3d as o3d

    from stages.common.registration import bound_open3d_threads, prepare_cloud

    prepare_cloud(np.random.default_rng(0).normal(size=(200, 3)), 0.0)
    return o3d.utility.get_max_threads(), bound_open3d_threads()


def test_open3d_runs_on_the_threads_a_dask_worker_was_given():
    """Open3D's oneTBB ignores the OMP_NUM_THREADS=1 of a dask worker: the first preparation or registration in a
    worker process bounds it to the worker's thread count (a process worker, so this process is not bounded)."""
    import os

    distributed = pytest.importorskip("distributed")
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: Open3D's default is already one thread")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        assert client.submit(_open3d_threads_after_a_registration, 0).result() == (1, 1)


def test_crop_range_keeps_the_band_inclusive_and_drops_non_finite_points():
    from stages.common.registration import crop_range

    rng = np.random.default_rng(4)
    pts = rng.normal(0.0, 30.0, (20000, 3))
    pts[:3] = [[2.0, 0.0, 0.0], [0.0, 0.0, -80.0], [np.nan, 1.0, 1.0]]
    pts[3:5] = [[np.inf, 0.0, 0.0], [0.0, -np.inf, 5.0]]
    norm_m = np.linalg.norm(pts, axis=1)
    expected = (norm_m >= 2.0) & (norm_m <= 80.0) & np.isfinite(norm_m)
    got = crop_range(pts, 2.0, 80.0)
    np.testing.assert_array_equal(got, expected)
    assert got[:2].all() and not got[2:5].any()
