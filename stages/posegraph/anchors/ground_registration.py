"""Height, roll and pitch of a keyframe from its ground points registered onto the survey, with the horizontal
position and heading held at the estimate.

Why not a 6-DoF registration: the survey holds road and sidewalk tops only, so it fixes the ground plane but
not the position along it. A 6-DoF GICP (open3d) of a scan's ground onto it slides along the road until its
iteration cap (measured on demo seed 1: 0.2-12 m after 50 iterations, 0.15-0.2 s per keyframe), and the tilt
it reports is that of wherever it stopped: capping it at 30 instead of 50 iterations moved the tilt by up to
0.18 deg and the height by up to 18 mm. Here the three free directions are the only unknowns, so the fit
measures the ground under the estimate and converges in a few Gauss-Newton steps.

Method (pure numpy / scipy): the scan's ground points are placed with the estimate; each is paired with the
survey point nearest to it horizontally (a height field: one surface per place), whose normal comes from the
survey's local plane. The height is started at the median vertical offset of the pairs (robust to any start
height, where a registration bounded by its correspondence distance finds nothing to pair beyond it), then
(droll, dpitch, dz) about the keyframe minimise the point-to-plane residuals by iteratively reweighted least
squares with Tukey's biweight of decreasing widths (kerbs, bumpers and a sidewalk seen through a horizontal
error weigh nothing; as ``stages.common.ground_plane`` does for a scan's own plane).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.registration import one_batch_tree

TUKEY_WIDTHS_M = (0.3, 0.15, 0.08, 0.05, 0.05, 0.05)  # the first after the median start, decreasing


@dataclass(frozen=True)
class VerticalFit:
    T_target_source: np.ndarray  # (4,4) the start with its height, roll and pitch corrected about its origin
    fitness: float  # share of source points with a survey point within max_corr_m (3-D) at the result
    inlier_rmse_m: float  # RMS 3-D distance of those pairs (open3d's definition, for the same gates)
    converged: bool  # False when too few points carried weight


def plane_normals(points_m: np.ndarray, knn: int = 20) -> np.ndarray:
    """(N,3) unit normals of the local planes (``registration.prepare_cloud``'s, ``knn`` neighbours, no
    downsampling), turned to point up (+z)."""
    from stages.common.registration import prepare_cloud

    n = np.asarray(prepare_cloud(points_m, 0.0, knn=knn, with_covariances=False).normals).copy()
    n[n[:, 2] < 0] *= -1.0
    return n


def _rotation_xy(a: float, b: float) -> np.ndarray:
    """Rotation by ``a`` about x then ``b`` about y (small angles about the keyframe's map axes)."""
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    Ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    return Ry @ Rx


def register_vertical(source_m: np.ndarray, target_m: np.ndarray, target_normals: np.ndarray,
                      T_init: np.ndarray, *, max_corr_m: float = 1.0, widths_m: tuple[float, ...] = TUKEY_WIDTHS_M,
                      min_points: int = 100) -> VerticalFit:
    """Correct ``T_init`` (target <- source, in a frame whose origin is near the keyframe) in height, roll and
    pitch only, rotating about the frame's origin: the source's x, y and heading stay the start's to second order.

    ``source_m`` (N,3) source-frame points; ``target_m`` (M,3) with up-pointing ``target_normals``. Pairs are
    horizontal nearest neighbours within ``max_corr_m``."""
    src = np.asarray(source_m, np.float64)[:, :3]
    tgt = np.asarray(target_m, np.float64)
    tree = one_batch_tree(tgt[:, :2])
    R0, t0 = np.asarray(T_init, float)[:3, :3], np.asarray(T_init, float)[:3, 3]
    placed = src @ R0.T + t0
    R_corr, dz = np.eye(3), 0.0

    def pairs(p: np.ndarray):
        dist, idx = tree.query(p[:, :2], distance_upper_bound=max_corr_m)
        ok = np.isfinite(dist)
        return ok, idx[ok]

    converged = False
    if len(src) >= min_points and len(tgt) >= 3:
        ok, idx = pairs(placed)
        if ok.sum() >= min_points:
            n = target_normals[idx]
            r = np.einsum("ij,ij->i", placed[ok] - tgt[idx], n)
            dz = float(np.median(-r / n[:, 2]))  # the height first: the median vertical offset of the pairs
            converged = True
            for width in widths_m:
                turned = placed @ R_corr.T
                p = turned + [0.0, 0.0, dz]
                ok, idx = pairs(p)
                q, n = tgt[idx], target_normals[idx]
                r = np.einsum("ij,ij->i", p[ok] - q, n)
                w = np.where(np.abs(r) < width, (1.0 - (r / width) ** 2) ** 2, 0.0)
                if np.count_nonzero(w) < min_points:
                    converged = False
                    break
                # model p = R_corr placed + dz e_z; d r / d(rotation about x, y) = ((R_corr placed) x n)_x, _y
                pxn = np.cross(turned[ok], n)
                J = np.column_stack([pxn[:, 0], pxn[:, 1], n[:, 2]])
                Jw = J * w[:, None]
                try:
                    da, db, ddz = -np.linalg.solve(Jw.T @ J, Jw.T @ r)
                except np.linalg.LinAlgError:
                    converged = False
                    break
                R_corr = _rotation_xy(da, db) @ R_corr
                dz += float(ddz)
    T = np.eye(4)
    T[:3, :3] = R_corr @ R0
    T[:3, 3] = R_corr @ t0 + [0.0, 0.0, dz]
    fitness, rmse = _fit_quality(src @ T[:3, :3].T + T[:3, 3], tgt, max_corr_m)
    return VerticalFit(T, fitness, rmse, converged)


def _fit_quality(points_m: np.ndarray, target_m: np.ndarray, max_corr_m: float) -> tuple[float, float]:
    """open3d's fitness and inlier RMSE: the share of points with a target point within ``max_corr_m`` (3-D) and
    the RMS of those distances."""
    if len(points_m) == 0 or len(target_m) == 0:
        return 0.0, float("inf")
    dist, _ = one_batch_tree(target_m).query(points_m, distance_upper_bound=max_corr_m)
    ok = np.isfinite(dist)
    if not ok.any():
        return 0.0, float("inf")
    return float(ok.mean()), float(np.sqrt(np.mean(dist[ok] ** 2)))
