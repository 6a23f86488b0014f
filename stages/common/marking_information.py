"""How much one scan's road markings tell about the pose at a place: the information of the marking likelihood.

The MCL and the EKF's marking update score a pose by ``gain * c``, ``c`` the mean of the distance likelihood field
``exp(-d^2 / 2 sigma^2)`` (d: distance to paint) at the scan's road-feature points placed by the pose, ``gain =
sharpness * min(F, effective_points)`` (Kim, Liu & Myung s.2.3; ``stages/evaluate/mcl.py``). Features are paint:
placed by the true pose they sit on painted cells. So the expected log-likelihood of a pose offset ``delta``
(east, north, heading) is ``gain * c(delta)`` with ``c(delta)`` the mean field value of the painted cells within
``feature_range_m`` moved by ``delta``; its curvature at 0 is the information one scan gives:
``I = -gain * Hessian(c)``, taken by central differences one raster cell (and, for the heading, one cell at the
points' median range) wide. A road of unbroken lines informs across it only; dashes, stop lines and crosswalks
inform along it. Pure numpy / OpenCV, arrays in, arrays out.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

Window = Callable[[float, float, float, float], tuple[np.ndarray, tuple[float, float], float]]


def likelihood_field(mask: np.ndarray, cell_m: float, sigma_m: float) -> np.ndarray:
    """exp(-d^2 / 2 sigma^2) of the distance from each cell centre to the nearest painted cell (OpenCV's exact
    distance transform; the MCL's ``distance_likelihood_field``)."""
    import cv2

    paint = np.asarray(mask) > 0
    if not paint.any():
        return np.zeros(paint.shape, np.float32)
    d = cv2.distanceTransform((~paint).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d *= np.float32(cell_m / sigma_m)
    return np.exp(-0.5 * d * d)


def _offsets(h_pos: float, h_yaw: float) -> np.ndarray:
    """(19, 3) offsets of the central-difference Hessian: 0, +-h on each axis, +-h on each pair of axes."""
    h = np.array([h_pos, h_pos, h_yaw])
    out = [np.zeros(3)]
    for i in range(3):
        for s in (1, -1):
            e = np.zeros(3)
            e[i] = s * h[i]
            out.append(e)
    for i in range(3):
        for j in range(i + 1, 3):
            for si in (1, -1):
                for sj in (1, -1):
                    e = np.zeros(3)
                    e[i], e[j] = si * h[i], sj * h[j]
                    out.append(e)
    return np.asarray(out)


def _hessian(c: np.ndarray, h_pos: float, h_yaw: float) -> np.ndarray:
    """Hessian from the 19 values of ``_offsets``'s order."""
    h = np.array([h_pos, h_pos, h_yaw])
    H = np.zeros((3, 3))
    for i in range(3):
        H[i, i] = (c[1 + 2 * i] - 2.0 * c[0] + c[2 + 2 * i]) / h[i] ** 2
    k = 7
    for i in range(3):
        for j in range(i + 1, 3):
            pp, pm, mp, mm = c[k:k + 4]
            H[i, j] = H[j, i] = (pp - pm - mp + mm) / (4.0 * h[i] * h[j])
            k += 4
    return H


def information_at(points_en_m: np.ndarray, field: np.ndarray, paint_rc: np.ndarray, origin_en_m: tuple[float, float],
                   cell_m: float, *, feature_range_m: float, sharpness: float, effective_points: float,
                   max_points: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    """Per point (N,2): the (3,3) information on (east, north, heading) of one scan's markings there and the
    painted cells within ``feature_range_m``. ``field`` and ``paint_rc`` (painted cells' (row, col), row 0 = north)
    are one window's, with its south-west corner ``origin_en_m``."""
    pts = np.asarray(points_en_m, float).reshape(-1, 2)
    n_rows, n_cols = field.shape
    e_paint = origin_en_m[0] + (paint_rc[:, 1] + 0.5) * cell_m
    n_paint = origin_en_m[1] + (n_rows - paint_rc[:, 0] - 0.5) * cell_m
    info = np.zeros((len(pts), 3, 3))
    count = np.zeros(len(pts), np.int64)
    for k, (pe, pn) in enumerate(pts):
        de, dn = e_paint - pe, n_paint - pn
        near = np.flatnonzero(de * de + dn * dn <= feature_range_m ** 2)
        count[k] = len(near)
        if len(near) < 3:
            continue
        if len(near) > max_points:  # evenly spaced, deterministic
            near = near[np.linspace(0, len(near) - 1, max_points).astype(np.int64)]
        x, y = de[near], dn[near]
        h_yaw = cell_m / max(float(np.median(np.hypot(x, y))), cell_m)
        vals = []
        for de_o, dn_o, dyaw in _offsets(cell_m, h_yaw):
            c, s = np.cos(dyaw), np.sin(dyaw)
            qe, qn = pe + de_o + c * x - s * y, pn + dn_o + s * x + c * y
            col = np.floor((qe - origin_en_m[0]) / cell_m).astype(np.int64)
            row = n_rows - 1 - np.floor((qn - origin_en_m[1]) / cell_m).astype(np.int64)
            inside = (row >= 0) & (row < n_rows) & (col >= 0) & (col < n_cols)
            v = np.zeros(len(x))
            v[inside] = field[row[inside], col[inside]]
            vals.append(v.mean())
        gain = sharpness * min(float(len(near)), effective_points)
        w, V = np.linalg.eigh(-gain * _hessian(np.asarray(vals), cell_m, h_yaw))
        info[k] = (V * np.clip(w, 0.0, None)) @ V.T
    return info, count


def marking_information(points_en_m: np.ndarray, window: Window, block_m: float, *, sigma_m: float,
                        feature_range_m: float, sharpness: float, effective_points: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``information_at`` for points anywhere: grouped by ``block_m`` squares, each block's window (the square and
    ``feature_range_m`` + 1 m around) fetched once with ``window(e0, n0, e1, n1) -> (mask, (e_sw, n_sw), cell_m)``
    and its likelihood field computed once. Returns ((N,3,3) information, (N,) painted cells in range)."""
    pts = np.asarray(points_en_m, float).reshape(-1, 2)
    info = np.zeros((len(pts), 3, 3))
    count = np.zeros(len(pts), np.int64)
    if len(pts) == 0:
        return info, count
    keys = np.floor(pts / block_m).astype(np.int64)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    reach = feature_range_m + 1.0
    for b, (bi, bj) in enumerate(uniq):
        sel = np.flatnonzero(inverse.ravel() == b)
        e0, n0 = bi * block_m - reach, bj * block_m - reach
        mask, origin, cell = window(e0, n0, e0 + block_m + 2 * reach, n0 + block_m + 2 * reach)
        paint_rc = np.argwhere(np.asarray(mask) > 0)
        if len(paint_rc) == 0:
            continue
        field = likelihood_field(mask, cell, sigma_m)
        info[sel], count[sel] = information_at(pts[sel], field, paint_rc, origin, cell,
                                               feature_range_m=feature_range_m, sharpness=sharpness,
                                               effective_points=effective_points)
    return info, count
