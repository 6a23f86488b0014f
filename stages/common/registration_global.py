"""Coarse global registration of two scans with no initial guess: FPFH features matched by RANSAC (Open3D), the
start of a fine registration (``registration.register_clouds``) for scans metres apart whose relative pose nothing
else gives (keyframe drives without a prior; a revisit in the opposite direction).

Both clouds are voxel-downsampled (``voxel_m``), given normals (``normal_radius_m``) and FPFH descriptors
(``feature_radius_m``, Rusu et al. 2009); RANSAC draws 3 mutual feature correspondences, keeps hypotheses whose
edge lengths agree within 10 % and whose correspondences lie within ``max_corr_m``, and stops at ``confidence``.
Open3D's RANSAC draws from its global generator: it is seeded (``seed``) before every call, so one process gives one
answer; the answer may differ with Open3D's thread count, which a caller refines anyway.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class GlobalMatch:
    T_target_source: np.ndarray  # 4x4
    fitness: float  # share of source voxels within max_corr_m of a target voxel after the match
    inlier_rmse_m: float
    n_correspondences: int  # RANSAC's inlier correspondences


def _features(points_m: np.ndarray, voxel_m: float, normal_radius_m: float, feature_radius_m: float):
    from stages.common.registration import bound_open3d_threads

    bound_open3d_threads()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_m, np.float64)[:, :3]))
    cloud = cloud.voxel_down_sample(voxel_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30))
    fpfh = _REG.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=feature_radius_m, max_nn=100))
    return cloud, fpfh


def register_global(source_points_m: np.ndarray, target_points_m: np.ndarray, *, voxel_m: float = 1.0,
                    normal_radius_m: float = 2.0, feature_radius_m: float = 5.0, max_corr_m: float = 1.5,
                    max_iterations: int = 100_000, confidence: float = 0.999, seed: int = 0) -> GlobalMatch:
    """T_target_source of two clouds (N,3) with no initial guess (module docstring). A cloud with fewer than 10
    voxels gives the identity with fitness 0."""
    src, f_src = _features(source_points_m, voxel_m, normal_radius_m, feature_radius_m)
    tgt, f_tgt = _features(target_points_m, voxel_m, normal_radius_m, feature_radius_m)
    if len(src.points) < 10 or len(tgt.points) < 10:
        return GlobalMatch(np.eye(4), 0.0, float("inf"), 0)
    o3d.utility.random.seed(int(seed))
    res = _REG.registration_ransac_based_on_feature_matching(
        src, tgt, f_src, f_tgt, True, max_corr_m, _REG.TransformationEstimationPointToPoint(False), 3,
        [_REG.CorrespondenceCheckerBasedOnEdgeLength(0.9), _REG.CorrespondenceCheckerBasedOnDistance(max_corr_m)],
        _REG.RANSACConvergenceCriteria(max_iterations, confidence))
    T = np.asarray(res.transformation, dtype=float).copy()
    if not np.isfinite(T).all():
        return GlobalMatch(np.eye(4), 0.0, float("inf"), 0)
    return GlobalMatch(T, float(res.fitness), float(res.inlier_rmse), int(len(res.correspondence_set)))
