"""The localizability layer's cells: the map drives' roads sampled, what each sample sees, the two filters'
predicted covariances (``localizability.predict_pass``), gathered per ``cell_m`` cell with a verdict.

``predict_cells`` is the tiles stage's entry point (arrays in, a dict of columns out, one row per cell and method).
"""
from __future__ import annotations

import numpy as np

from stages.common.corner_visibility import visible, wall_segments
from stages.common.localizability import Corners, LocalizabilityConfig, predict_pass, resample_path
from stages.common.marking_information import Window, marking_information

METHODS = ("ekf", "mcl")
COLUMNS = ("cell_i", "cell_j", "method", "east_m", "north_m", "heading_rad", "sigma_along_m", "sigma_cross_m",
           "sigma_2d_m", "sigma_heading_deg", "cov_ee_m2", "cov_en_m2", "cov_nn_m2", "n_corners_visible",
           "n_wall_axes", "n_marking_px", "n_samples", "status", "reason")


def sample_step_m(paths_en_m: list[np.ndarray], floor_m: float) -> float:
    """One scan's travel at the drives' median moving speed (poses are per scan), at least ``floor_m``, at most 2 m."""
    steps = np.concatenate([np.linalg.norm(np.diff(np.asarray(p, float).reshape(-1, 2), axis=0), axis=1)
                            for p in paths_en_m if len(p) > 1] or [np.zeros(0)])
    moving = steps[steps > 0.05]
    return float(np.clip(np.median(moving) if len(moving) else floor_m, floor_m, 2.0))


def corners_in_view(points_en_m: np.ndarray, corners: Corners, cfg: LocalizabilityConfig,
                    chunk: int = 256) -> list[np.ndarray]:
    """Per point, the corner rows it sees (``corner_visibility.visible`` with the rebuilt walls), in chunks so
    memory follows the corners near the chunk, not the map."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points_en_m, float).reshape(-1, 2)
    out = [np.zeros(0, np.int64)] * len(pts)
    if len(corners.en_m) == 0 or len(pts) == 0:
        return out
    rng = cfg.ekf.sensor_range_m
    segs = wall_segments(corners.en_m, corners.theta_rad, stub_m=cfg.wall_stub_m)
    tree = cKDTree(corners.en_m)
    seg_mid = segs.mean(axis=1) if len(segs) else np.zeros((0, 2))
    seg_half = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1) / 2 if len(segs) else np.zeros(0)
    for a in range(0, len(pts), chunk):
        p = pts[a:a + chunk]
        cand = np.unique(np.concatenate([np.asarray(c, np.int64) for c in tree.query_ball_point(p, rng)]))
        if len(cand) == 0:
            continue
        lo, hi = p.min(axis=0) - rng, p.max(axis=0) + rng
        near = np.all((seg_mid >= lo[None] - seg_half[:, None]) & (seg_mid <= hi[None] + seg_half[:, None]), axis=1)
        vis = visible(p, corners.en_m[cand], corners.theta_rad[cand], corners.convex[cand], range_m=rng,
                      min_incidence_rad=np.deg2rad(cfg.min_incidence_deg), segments=segs[near])
        for k in range(len(p)):
            out[a + k] = cand[vis[k]]
    return out


def _wall_axes(theta_rad: np.ndarray, bin_deg: float = 15.0) -> int:
    """Distinct wall axes (directions mod 180 deg, ``bin_deg`` bins) among walls (any shape)."""
    if theta_rad.size == 0:
        return 0
    return len(np.unique(np.floor(np.degrees(np.mod(theta_rad.ravel(), np.pi)) / bin_deg).astype(int) %
                         int(round(180 / bin_deg))))


def _verdict(method: str, sigma_2d: float, n_vis: float, axes: int, cfg: LocalizabilityConfig) -> tuple[str, str]:
    reasons = []
    if method == "ekf" and n_vis < 1:
        reasons.append("no corner in view")
    elif method == "ekf" and n_vis < 2:
        reasons.append("one corner in view")
    if method == "ekf" and n_vis >= 1 and axes < 2:
        reasons.append("walls in one direction")
    if sigma_2d > cfg.weak_sigma_m:
        reasons.append(f"sigma_2d {sigma_2d:.2f} m > {cfg.weak_sigma_m:g} m")
    status = "fail" if sigma_2d > cfg.fail_sigma_m else "weak" if reasons else "ok"
    return status, "; ".join(reasons)


def predict_cells(paths_en_m: list[np.ndarray], corners: Corners, window: Window | None,
                  cfg: LocalizabilityConfig = LocalizabilityConfig()) -> dict[str, list]:
    """Columns (``COLUMNS``) of the localizability layer: one row per cell the drives cross and per method."""
    step = sample_step_m(paths_en_m, max(cfg.ekf.corner_decorrelation_m, cfg.markings.decorrelation_m))
    passes = [resample_path(p, step) for p in paths_en_m]
    passes = [(p, y) for p, y in passes if len(p)]
    out: dict[str, list] = {c: [] for c in COLUMNS}
    if not passes:
        return out
    pts = np.vstack([p for p, _ in passes])
    yaw = np.concatenate([y for _, y in passes])
    start = np.concatenate([np.arange(len(p)) * step < cfg.burn_in_m for p, _ in passes])
    keys = np.floor(pts / cfg.cell_m).astype(np.int64)
    cells, cell_of = np.unique(keys, axis=0, return_inverse=True)
    cell_of = cell_of.ravel()
    rep = np.zeros((len(cells), 2))
    for c in range(len(cells)):
        sel = pts[cell_of == c]
        rep[c] = sel[np.argmin(np.linalg.norm(sel - sel.mean(axis=0), axis=1))]
    if window is not None:
        mk = cfg.markings
        info_cell, paint = marking_information(rep, window, 100.0, sigma_m=mk.raster_sigma_m,
                                               feature_range_m=mk.feature_max_range_m, sharpness=mk.sharpness,
                                               effective_points=mk.effective_points)
    else:
        info_cell, paint = np.zeros((len(cells), 3, 3)), np.zeros(len(cells), np.int64)
    in_view = corners_in_view(pts, corners, cfg)
    covs = {}
    for method in METHODS:
        parts, a = [], 0
        for p, y in passes:
            b = a + len(p)
            parts.append(predict_pass(p, y, step, method, corners, in_view[a:b], info_cell[cell_of[a:b]], cfg))
            a = b
        covs[method] = np.concatenate(parts)
    n_vis = np.array([len(v) for v in in_view])
    for c, (ci, cj) in enumerate(cells):
        sel = np.flatnonzero(cell_of == c)
        if (~start[sel]).any():
            sel = sel[~start[sel]]
        axial = np.angle(np.exp(2j * yaw[sel]).mean()) / 2.0
        seen = np.unique(np.concatenate([in_view[k] for k in sel]))
        axes = _wall_axes(corners.theta_rad[seen]) if len(seen) else 0
        nv = float(np.median(n_vis[sel]))
        for method in METHODS:
            P = covs[method][sel].mean(axis=0)
            Rot = np.array([[np.cos(axial), np.sin(axial)], [-np.sin(axial), np.cos(axial)]])
            A = Rot @ P[:2, :2] @ Rot.T
            s2d = float(np.sqrt(P[0, 0] + P[1, 1]))
            status, reason = _verdict(method, s2d, nv, axes, cfg)
            for col, v in (("cell_i", int(ci)), ("cell_j", int(cj)), ("method", method), ("east_m", rep[c, 0]),
                           ("north_m", rep[c, 1]), ("heading_rad", float(axial)),
                           ("sigma_along_m", float(np.sqrt(A[0, 0]))), ("sigma_cross_m", float(np.sqrt(A[1, 1]))),
                           ("sigma_2d_m", s2d), ("sigma_heading_deg", float(np.degrees(np.sqrt(P[2, 2])))),
                           ("cov_ee_m2", float(P[0, 0])), ("cov_en_m2", float(P[0, 1])),
                           ("cov_nn_m2", float(P[1, 1])), ("n_corners_visible", int(round(nv))),
                           ("n_wall_axes", int(axes)), ("n_marking_px", int(paint[c])), ("n_samples", len(sel)),
                           ("status", status), ("reason", reason)):
                out[col].append(v)
    return out
