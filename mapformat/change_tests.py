"""Statistical change detection between two versions of a map: corners by a chi-square test on their covariances,
road markings per cell against the rasters' own noise. Used by the changelog (a version against its parent) and
``tiles diff`` (any two versions). Pure numpy / scipy, arrays in, arrays out.

Corners. A corner kept from version A to B (matched by identity or geometry) moved by ``d`` (east, north). Under
"unchanged" ``d ~ N(0, C_A + C_B)`` (the two maps' errors taken as independent: conservative when they share
drives), so ``chi2 = d^T (C_A + C_B)^-1 d`` follows a chi-square law with 2 degrees of freedom; the corner is
``moved`` when chi2 exceeds its ``1 - significance`` quantile (significance 0.001: 13.82). A corner of A not
matched in B is ``removed`` when B's drives had it in view (``corner_visibility.visible`` from B's roads) from at
least as many scans as the corner map needs observations to keep a corner (``min_obs``), else ``not_reobserved``;
a corner of B not matched in A is ``added`` by the same rule on A's drives, else ``newly_observed``. Absence is not
a statistical test: a drive's scans are not independent looks (a vehicle ahead hides a corner for a whole pass),
and one pass cannot show at 0.001 that a corner is gone; the false alarms this rule gives on an unchanged re-drive
are measured (docs/map-format.md).

Markings. Two surveys of unchanged paint differ at its edges: a cell counts as changed where one version paints
and the other has no paint within ``tolerance_px`` cells, among cells both versions observed (point_count > 0).
Per ``cell_m`` cell: n = cells painted in either version, x = changed cells. The noise rate ``p0`` is the median of
x / n over the compared cells (most of a city does not change between two versions) and a cell is changed when
``P(X >= x | n, p0)`` (binomial) is below ``significance / number of cells compared`` (Bonferroni) and x is at
least ``min_changed_px``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SIGNIFICANCE = 0.001
DOF = 2


def chi2_threshold(significance: float = SIGNIFICANCE, dof: int = DOF) -> float:
    from scipy.stats import chi2

    return float(chi2.ppf(1.0 - significance, dof))


def corner_chi2(d_en_m: np.ndarray, cov_a_m2: np.ndarray, cov_b_m2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) chi-square statistics and p-values of (K,2) displacements with (K,2,2) covariances of both versions."""
    from scipy.stats import chi2

    d = np.asarray(d_en_m, float).reshape(-1, 2)
    S = np.asarray(cov_a_m2, float).reshape(-1, 2, 2) + np.asarray(cov_b_m2, float).reshape(-1, 2, 2)
    S = S + 1e-12 * np.eye(2)  # a zero covariance (a synthetic map) stays invertible
    stat = np.einsum("ki,ki->k", d, np.linalg.solve(S, d[:, :, None])[:, :, 0]) if len(d) else np.zeros(0)
    return stat, chi2.sf(stat, DOF)


def looks_from(paths_en_m: list[np.ndarray], corners_en_m: np.ndarray, theta_rad: np.ndarray, convex: np.ndarray,
               range_m: float = 60.0) -> np.ndarray:
    """(K,) how many scans of the drives (each path resampled at one scan's travel, its median moving step) see each
    corner (range, the walls' seen side, the rebuilt walls: ``corner_visibility.visible``)."""
    from scipy.spatial import cKDTree

    from stages.common.corner_visibility import visible, wall_segments
    from stages.common.localizability import resample_path
    from stages.common.localizability_cells import sample_step_m

    c = np.asarray(corners_en_m, float).reshape(-1, 2)
    out = np.zeros(len(c), np.int64)
    paths = [np.asarray(p, float).reshape(-1, 2) for p in paths_en_m if len(p) > 1]
    if len(c) == 0 or not paths:
        return out
    pts = np.vstack([resample_path(p, sample_step_m([p], 0.1))[0] for p in paths])
    if len(pts) == 0:
        return out
    near = np.flatnonzero(np.isfinite(cKDTree(pts).query(c, distance_upper_bound=range_m)[0]))
    if len(near) == 0:
        return out
    segs = wall_segments(np.asarray(corners_en_m, float), np.asarray(theta_rad, float))
    for a in range(0, len(pts), 256):
        vis = visible(pts[a:a + 256], c[near], np.asarray(theta_rad)[near], np.asarray(convex, bool)[near],
                      range_m=range_m, segments=segs)
        out[near] += vis.sum(axis=0)
    return out


def seen_from(paths_en_m: list[np.ndarray], corners_en_m: np.ndarray, theta_rad: np.ndarray, convex: np.ndarray,
              range_m: float = 60.0) -> np.ndarray:
    """(K,) True where some scan of the drives sees the corner (``looks_from`` > 0)."""
    return looks_from(paths_en_m, corners_en_m, theta_rad, convex, range_m) > 0


@dataclass(frozen=True)
class MarkingCells:
    """Per compared cell: key (cell_i, cell_j), painted-in-either count n, changed count x."""

    keys: np.ndarray  # (M,2) int64
    n: np.ndarray  # (M,)
    x: np.ndarray  # (M,)


def tile_cells(mask_a: np.ndarray | None, mask_b: np.ndarray | None, observed: np.ndarray,
               origin_en_m: tuple[float, float], cell_m: float, region_m: float, tolerance_px: int) -> MarkingCells:
    """One tile's cells (``region_m`` squares of the ENU grid) compared: masks (row 0 north, same lattice; None = no
    paint) over the cells both versions observed."""
    import cv2

    shape = observed.shape
    a = np.zeros(shape, bool) if mask_a is None else np.asarray(mask_a).reshape(shape[0], shape[1], -1).any(axis=2)
    b = np.zeros(shape, bool) if mask_b is None else np.asarray(mask_b).reshape(shape[0], shape[1], -1).any(axis=2)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance_px + 1, 2 * tolerance_px + 1))
    a_near = cv2.dilate(a.astype(np.uint8), kernel) > 0
    b_near = cv2.dilate(b.astype(np.uint8), kernel) > 0
    obs = np.asarray(observed, bool)
    union = (a | b) & obs
    changed = ((a & ~b_near) | (b & ~a_near)) & obs
    rows, cols = np.nonzero(union)
    if len(rows) == 0:
        return MarkingCells(np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    east = origin_en_m[0] + (cols + 0.5) * cell_m
    north = origin_en_m[1] + (shape[0] - rows - 0.5) * cell_m
    keys = np.column_stack([np.floor(east / region_m), np.floor(north / region_m)]).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    return MarkingCells(uniq, np.bincount(inv, minlength=len(uniq)),
                        np.bincount(inv, weights=changed[rows, cols], minlength=len(uniq)).astype(np.int64))


def changed_cells(cells: list[MarkingCells], region_m: float, significance: float = SIGNIFICANCE,
               min_changed_px: int = 20) -> tuple[list[dict], dict]:
    """The changed cells (dicts: cell, east_m / north_m of its centre, px_changed, px_compared, p_value) and the
    test's description (method, noise rate, significance, cells compared)."""
    from scipy.stats import binom

    keys = np.vstack([c.keys for c in cells]) if cells else np.zeros((0, 2), np.int64)
    n = np.concatenate([c.n for c in cells]) if cells else np.zeros(0, np.int64)
    x = np.concatenate([c.x for c in cells]) if cells else np.zeros(0, np.int64)
    if len(keys):  # a cell split over two tiles' rasters: one cell
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        keys, n, x = uniq, np.bincount(inv, n, len(uniq)).astype(np.int64), np.bincount(inv, x, len(uniq)).astype(
            np.int64)
    rate = float(np.median(x / np.maximum(n, 1))) if len(n) else 0.0
    p0 = max(rate, 1.0 / max(int(n.sum()), 1))
    p = binom.sf(x - 1, n, p0) if len(n) else np.zeros(0)
    alpha = significance / max(len(n), 1)
    hit = np.flatnonzero((p < alpha) & (x >= min_changed_px))
    out = [{"cell": [int(keys[k, 0]), int(keys[k, 1])], "east_m": round((keys[k, 0] + 0.5) * region_m, 2),
            "north_m": round((keys[k, 1] + 0.5) * region_m, 2), "px_changed": int(x[k]), "px_compared": int(n[k]),
            "p_value": float(p[k])} for k in hit]
    test = {"method": "binomial per cell against the median changed share (Bonferroni)", "noise_rate": round(p0, 5),
            "significance": significance, "cells_compared": int(len(n)), "min_changed_px": int(min_changed_px)}
    return out, test
