"""Scan-to-scan registration on voxel-downsampled clouds (open3d) and edge information matrices (deskewing:
``stages.common.deskew``).

Pure functions: numpy arrays and open3d clouds in, numpy out. ``T_a_b`` maps points of frame b into frame a.
Information matrices are 6x6 in gtsam's tangent order (rx ry rz tx ty tz) for a *right* (body-frame)
perturbation of the returned transform, i.e. directly usable by ``gtsam.BetweenFactorPose3``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from stages.common.geometry import skew

_REG = o3d.pipelines.registration
METHODS = ("gicp", "point_to_plane")


@functools.cache  # once per process, at its first preparation or registration
def bound_open3d_threads() -> int | None:
    """On a dask worker or in a process of a local pool, bound Open3D to the cores the task may use
    (``pipeline.parallel.task_threads``), once per process: Open3D 0.20 runs on oneTBB, which ignores the
    ``OMP_NUM_THREADS=1`` a dask nanny or a pool sets, so a "single-threaded" worker ran its registrations on every
    core of the machine. Measured on demo seed 1, a LocalCluster of single-threaded workers: 1 worker 254.2 s
    unbounded, 289.3 s bounded; 2 workers 168.6 / 160.7 s; the odometry on a local pool of 2 processes: 62.5-63.4 s
    unbounded, 59.9-60.6 s bounded. Elsewhere (a sync run, a script) Open3D keeps its own default. Returns the bound
    (None: none set)."""
    from pipeline.parallel import task_threads

    n = task_threads()
    if n and hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(n)
    return n


@dataclass(frozen=True)
class RegistrationResult:
    T_target_source: np.ndarray  # 4x4
    fitness: float  # share of source points with a correspondence within max_corr
    inlier_rmse_m: float
    information: np.ndarray  # 6x6, gtsam order, body frame of T_target_source
    converged: bool
    hessian: np.ndarray  # the unfloored point-to-plane Hessian behind ``information`` (6x6)


def as_indices(found: list[int]) -> np.ndarray:
    """A ``cKDTree.query_ball_point`` answer for one point (a list of Python ints) as an index array, in its order,
    converted once: numpy converts a list again at each fancy indexing (65,606 indices: 0.73 ms each; this 0.61 ms).
    """
    return np.fromiter(found, np.intp, len(found))


def one_batch_tree(points_m: np.ndarray):
    """A scipy ``cKDTree`` for a tree built, queried once or a few times and dropped (a crop, a scan): split at the
    midpoint and not compacted, which builds it ~2x faster than the default balanced, compacted tree for slightly
    slower queries; the nearest neighbours are the same. A survey crop of 56k points with seven 2-D queries and one
    3-D query of 6k points: 38.2 -> 25.2 ms."""
    from scipy.spatial import cKDTree

    return cKDTree(points_m, balanced_tree=False, compact_nodes=False)


def voxel_downsample(points_m: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,3) points -> the mean point of each occupied voxel of ``voxel_m`` (Open3D's ``voxel_down_sample``), as a
    float64 array; ``voxel_m`` <= 0: the points unchanged (as ``prepare_cloud``)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_m, np.float64)[:, :3]))
    return np.asarray((cloud.voxel_down_sample(voxel_m) if voxel_m > 0 else cloud).points)


def crop_range(points_m: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """Boolean mask of points whose range from the sensor lies in [min, max] (a NaN or infinite coordinate: out).
    Squared ranges against squared bounds: 0.54 -> 0.10 ms a 39k-point scan against ``np.linalg.norm``, the same
    masks on 200 demo scans."""
    x, y, z = points_m[:, 0], points_m[:, 1], points_m[:, 2]
    range2_m2 = x * x + y * y + z * z
    return (range2_m2 >= min_range_m * min_range_m) & (range2_m2 <= max_range_m * max_range_m)


MIN_COVARIANCE_EIGENVALUE_M2 = 1e-6  # (1 mm)^2: see regularize_covariances


def regularize_covariances(covariances_m2: np.ndarray, min_eigenvalue_m2: float) -> np.ndarray:
    """(N,3,3) point covariances plus ``min_eigenvalue_m2`` times the identity: every eigenvalue at least that,
    the eigenvectors (plane normals, line directions) unchanged; O(N), unlike an eigenvalue clamp.

    GICP inverts C_target + R C_source R^T per correspondence. A neighbourhood that lies exactly in a plane or
    on a line (one lidar ring: a beam at 0 deg elevation gives points of one constant height in the sensor
    frame, and a simulator adds range noise only along the ray) has a zero eigenvalue; two such
    neighbourhoods with the same null direction make that sum singular and open3d's GICP diverges to NaN.
    Measured on the `gangnam` simulation: 87 % of the 413 rejected odometry edges of drive 0. An isotropic
    (1 mm)^2 keeps the shapes (planar patches are 0.3-1 mm thick after voxel averaging) and makes every sum
    invertible.
    """
    return covariances_m2 + min_eigenvalue_m2 * np.eye(3)


def prepare_cloud(points_m: np.ndarray, voxel_m: float, knn: int = 20, with_covariances: bool = True,
                  min_cov_eigenvalue_m2: float = MIN_COVARIANCE_EIGENVALUE_M2) -> o3d.geometry.PointCloud:
    """Voxel-downsample and attach per-point covariances (GICP; regularised, see ``regularize_covariances``)
    or normals (point-to-plane)."""
    bound_open3d_threads()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_m[:, :3], dtype=np.float64)))
    if voxel_m > 0:
        cloud = cloud.voxel_down_sample(voxel_m)
    search = o3d.geometry.KDTreeSearchParamKNN(knn)
    if with_covariances:
        cloud.estimate_covariances(search)
        if min_cov_eigenvalue_m2 > 0 and cloud.has_covariances():  # False for an empty cloud
            # in place, through the numpy view of open3d's buffer (building a new Matrix3dVector from numpy
            # cost 2.7 ms per 4k-point scan, a quarter of the cloud's preparation)
            covariances_m2 = np.asarray(cloud.covariances)
            covariances_m2[:] = regularize_covariances(covariances_m2, min_cov_eigenvalue_m2)
    cloud.estimate_normals(search)
    return cloud


def adjoint_se3(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint in (rot, trans) order: T Exp(xi) T^-1 = Exp(Ad_T xi)."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad


def point_to_plane_hessian(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
                           T_target_source: np.ndarray, max_corr_m: float, point_sigma_m: float,
                           correspondences: np.ndarray | None = None) -> np.ndarray:
    """Gauss-Newton Hessian (6x6, body frame, gtsam order) of the point-to-plane residuals of an alignment.

    Each source point p (moved by T) with its nearest target point q and normal n within ``max_corr_m``
    contributes J = [p x n, n] / point_sigma_m for a left perturbation in the target frame; the sum is moved to
    the body frame with the adjoint. Hessians of disjoint point sets (ground, structure) add up.
    ``correspondences`` ((K, 2) source / target indices at ``T_target_source``, e.g. open3d's
    ``correspondence_set`` of the registration that ended there) replaces the nearest-neighbour search.
    """
    src = np.asarray(source.points) @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    tgt = np.asarray(target.points)
    normals = np.asarray(target.normals)
    if len(src) == 0 or len(tgt) == 0 or len(normals) != len(tgt):
        return np.zeros((6, 6))
    if correspondences is None:
        dist_m, idx = one_batch_tree(tgt).query(src, distance_upper_bound=max_corr_m)
        ok = np.isfinite(dist_m)
        p, n = src[ok], normals[idx[ok]]
    else:
        pairs = np.asarray(correspondences, dtype=np.int64).reshape(-1, 2)
        p, n = src[pairs[:, 0]], normals[pairs[:, 1]]
    return _body_hessian(p, n, T_target_source, point_sigma_m)


def _body_hessian(p: np.ndarray, n: np.ndarray, T_target_source: np.ndarray, point_sigma_m: float) -> np.ndarray:
    """The point-to-plane Hessian of moved source points ``p`` on target planes of normals ``n`` (each (K,3), or one
    (3,) normal for every point), in the body frame."""
    n = np.broadcast_to(n, p.shape)
    J = np.hstack([np.cross(p, n), n])
    H_target = J.T @ J / point_sigma_m ** 2
    Ad = adjoint_se3(T_target_source)
    return Ad.T @ H_target @ Ad


def plane_hessian(source_m: np.ndarray, target_m: np.ndarray, normal: np.ndarray, T_target_source: np.ndarray,
                  max_corr_m: float, point_sigma_m: float) -> np.ndarray:
    """``point_to_plane_hessian`` of points lying on one fitted plane (a scan's road): every source point (moved
    by T) with a target point within ``max_corr_m`` constrains along the plane's ``normal`` (target frame), not
    along per-point normals estimated from the target's neighbours. A plane constrains height, roll and pitch only;
    the estimated normals of a noisy road tilt at random and credited the edge with horizontal information the
    road does not hold. Needs no normal estimation (the ground's KNN normals were 7 % of a single-threaded odometry
    on demo seed 1)."""
    src = np.asarray(source_m, np.float64) @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    tgt = np.asarray(target_m, np.float64)
    if len(src) == 0 or len(tgt) == 0:
        return np.zeros((6, 6))
    dist_m, _ = one_batch_tree(tgt).query(src, distance_upper_bound=max_corr_m)
    return _body_hessian(src[np.isfinite(dist_m)], np.asarray(normal, np.float64), T_target_source, point_sigma_m)


def floor_information(H: np.ndarray, min_sigma_m: float, min_sigma_rad: float) -> np.ndarray:
    """Cap an information matrix so that its covariance is at least diag(min_sigma)^2 (PSD sum).

    The point-to-plane Hessian keeps directions the scene does not constrain (a tunnel's axis) weak; its
    covariance is floored because ICP residuals are correlated and the raw Hessian is overconfident."""
    H = 0.5 * (H + H.T)
    floor_cov = np.diag([min_sigma_rad ** 2] * 3 + [min_sigma_m ** 2] * 3)
    w, V = np.linalg.eigh(H)
    w = np.maximum(w, 1e-9)
    cov = (V / w) @ V.T + floor_cov
    info = np.linalg.inv(cov)
    return 0.5 * (info + info.T)


def register_clouds(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T_init: np.ndarray, *,
                    method: str = "gicp", max_corr_m: float = 1.0, max_iterations: int = 30,
                    point_sigma_m: float = 0.05, min_sigma_m: float = 0.005,
                    min_sigma_rad: float = 0.0002, relative_tolerance: float = 1e-6) -> RegistrationResult:
    """Align ``source`` onto ``target`` starting from ``T_init`` (T_target_source)."""
    bound_open3d_threads()
    criteria = _REG.ICPConvergenceCriteria(relative_fitness=relative_tolerance,
                                           relative_rmse=relative_tolerance, max_iteration=max_iterations)
    if method == "gicp":
        res = _REG.registration_generalized_icp(source, target, max_corr_m, T_init,
                                                _REG.TransformationEstimationForGeneralizedICP(), criteria)
    elif method == "point_to_plane":
        res = _REG.registration_icp(source, target, max_corr_m, T_init,
                                    _REG.TransformationEstimationPointToPlane(), criteria)
    else:  # validated by params; kept for direct callers
        raise ValueError(f"registration method {method!r} unknown; expected one of {METHODS}")
    T = np.asarray(res.transformation, dtype=float).copy()
    if not np.isfinite(T).all():  # GICP on degenerate covariances can diverge to NaN
        return RegistrationResult(np.asarray(T_init, float).copy(), 0.0, float("inf"),
                                  floor_information(np.zeros((6, 6)), min_sigma_m, min_sigma_rad), False,
                                  np.zeros((6, 6)))
    # open3d's correspondences are those of the returned transformation (same nearest neighbours within
    # max_corr_m as a fresh search: checked on gangnam scans, and by tests/stages/common/test_registration.py)
    H = point_to_plane_hessian(source, target, T, max_corr_m, point_sigma_m, np.asarray(res.correspondence_set))
    converged = bool(res.fitness > 0 and np.isfinite(T).all())
    return RegistrationResult(T, float(res.fitness), float(res.inlier_rmse),
                              floor_information(H, min_sigma_m, min_sigma_rad), converged, H)


@dataclass(frozen=True)
class AlignmentScore:
    inlier_share: float  # share of source points lying on a target surface (plane distance < plane_tol_m)
    plane_rmse_m: float  # RMS point-to-plane distance of the inliers (target normals)


def score_alignment(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T_target_source: np.ndarray,
                    search_m: float, plane_tol_m: float = 0.1) -> AlignmentScore:
    """Tight quality of an alignment that does not depend on the ring pattern: a source point is an inlier
    when its nearest target point lies within ``search_m`` and its distance to that point's tangent plane is
    below ``plane_tol_m``. (open3d's inlier RMSE is point-to-point between sparse rings, ~0.5 m on 0.4 m
    voxels whatever the pose; two scans of one place taken 3 m apart rarely share ring positions.)"""
    src = np.asarray(source.points) @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    tgt = np.asarray(target.points)
    normals = np.asarray(target.normals)
    if len(src) == 0 or len(tgt) == 0 or len(normals) != len(tgt) or not np.isfinite(src).all():
        return AlignmentScore(0.0, float("inf"))
    dist_m, idx = one_batch_tree(tgt).query(src, distance_upper_bound=search_m)
    ok = np.isfinite(dist_m)
    plane_m = np.abs(np.einsum("ij,ij->i", src[ok] - tgt[idx[ok]], normals[idx[ok]]))
    inl = plane_m < plane_tol_m
    if not inl.any():
        return AlignmentScore(0.0, float("inf"))
    return AlignmentScore(float(inl.sum() / len(src)), float(np.sqrt(np.mean(plane_m[inl] ** 2))))


def register_coarse_to_fine(source_points_m: np.ndarray, target_points_m: np.ndarray, T_init: np.ndarray, *,
                            stages: tuple[tuple[float, float], ...] = ((1.0, 3.0), (0.4, 1.0), (0.4, 0.5)),
                            max_iterations: int = 40, point_sigma_m: float = 0.05, min_sigma_m: float = 0.005,
                            min_sigma_rad: float = 0.0002, relative_tolerance: float = 1e-6,
                            prepared: dict | None = None, keys: tuple = ("source", "target")
                            ) -> tuple[RegistrationResult, o3d.geometry.PointCloud, o3d.geometry.PointCloud]:
    """GICP in stages of (voxel_m, max_corr_m), each starting from the previous result, so that an initial
    guess 1-2 m off (two GNSS epochs of different passes) is first pulled in on coarse voxels with a wide
    correspondence distance, then refined. Returns the last stage's result and its (source, target) clouds.

    ``prepared``: a dict that keeps the prepared clouds under ``(key, voxel_m)`` (``keys`` name the source and the
    target), so that registering the same points again (another start, another pair with the same scan) does not
    prepare them again; the result is the same (preparation is deterministic and GICP does not change the clouds)."""
    T = np.asarray(T_init, float)
    cache = {} if prepared is None else prepared
    res = None
    for voxel_m, corr_m in stages:
        for key, pts in zip(keys, (source_points_m, target_points_m)):
            if (key, voxel_m) not in cache:
                cache[(key, voxel_m)] = prepare_cloud(pts, voxel_m)
        src, tgt = cache[(keys[0], voxel_m)], cache[(keys[1], voxel_m)]
        res = register_clouds(src, tgt, T, method="gicp", max_corr_m=corr_m, max_iterations=max_iterations,
                              point_sigma_m=point_sigma_m, min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad,
                              relative_tolerance=relative_tolerance)
        if not res.converged:
            return res, src, tgt
        T = res.T_target_source
    return res, src, tgt
