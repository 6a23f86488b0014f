"""Pure algorithms of the tiles stage: grouping by tile, driven-path measures, quality gates.

Arrays in, arrays (or lists of problems) out; no paths, no tables.
"""
from __future__ import annotations

import numpy as np

from stages.common.tiling import tile_key_of


def group_by_tile(east_m: np.ndarray, north_m: np.ndarray, size_m: float) -> dict[tuple[int, int], np.ndarray]:
    """Tile key -> indices of the points in it (ascending), half-open tile bounds."""
    i, j = tile_key_of(east_m, north_m, size_m)
    if i.size == 0:
        return {}
    keys = np.column_stack([i, j])
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind="stable")
    splits = np.cumsum(np.bincount(inverse.ravel(), minlength=len(uniq)))[:-1]
    return {(int(k[0]), int(k[1])): idx for k, idx in zip(uniq, np.split(order, splits))}


def path_length_m(xy_m: np.ndarray) -> float:
    """Length of one polyline (N,2)."""
    if len(xy_m) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(xy_m, axis=0), axis=1).sum())


def distinct_path_length_m(paths_xy_m: list[np.ndarray], step_m: float, radius_m: float) -> float:
    """Length of the streets the paths drove, each counted once: the paths in order, each segment of a path
    (densified to ``step_m``) counted when its midpoint lies farther than ``radius_m`` from every earlier path. A
    second lap of a street, in either lane, adds nothing; one path alone is its own length (to the densification)."""
    from scipy.spatial import cKDTree

    total, earlier = 0.0, []
    for xy in paths_xy_m:
        dense = densify_path(xy, step_m)
        if len(dense) < 2:
            continue
        seg = np.linalg.norm(np.diff(dense, axis=0), axis=1)
        if earlier:
            mid = 0.5 * (dense[1:] + dense[:-1])
            far = cKDTree(np.vstack(earlier)).query(mid, distance_upper_bound=radius_m)[0] > radius_m
            total += float(seg[far].sum())
        else:
            total += float(seg.sum())
        earlier.append(dense)
    return total


def densify_path(xy_m: np.ndarray, step_m: float) -> np.ndarray:
    """Insert points so that consecutive points are at most ``step_m`` apart (keeps the originals)."""
    xy_m = np.asarray(xy_m, float).reshape(-1, 2)
    if len(xy_m) < 2:
        return xy_m
    seg = np.diff(xy_m, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / step_m).astype(np.int64))
    seg_idx = np.repeat(np.arange(len(seg)), n)
    frac = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    pts = xy_m[seg_idx] + seg[seg_idx] * frac[:, None]
    return np.vstack([pts, xy_m[-1:]])


def path_tiles(paths_xy_m: list[np.ndarray], size_m: float, step_m: float) -> set[tuple[int, int]]:
    """Tiles the driven paths pass through."""
    keys: set[tuple[int, int]] = set()
    for xy in paths_xy_m:
        dense = densify_path(xy, step_m)
        if len(dense):
            i, j = tile_key_of(dense[:, 0], dense[:, 1], size_m)
            keys.update(zip(i.tolist(), j.tolist()))
    return keys


def check_corner_values(corner_id: np.ndarray, east_m: np.ndarray, north_m: np.ndarray, theta1_rad: np.ndarray,
                        theta2_rad: np.ndarray, cov_ee_m2: np.ndarray, cov_en_m2: np.ndarray,
                        cov_nn_m2: np.ndarray, tol_m2: float = 1e-12) -> list[str]:
    """Value-level validity of a corner map: finite, PSD 2x2 covariances, unique ids."""
    problems = []
    for name, arr in (("east_m", east_m), ("north_m", north_m), ("theta1_rad", theta1_rad),
                      ("theta2_rad", theta2_rad), ("cov_ee_m2", cov_ee_m2), ("cov_en_m2", cov_en_m2),
                      ("cov_nn_m2", cov_nn_m2)):
        bad = ~np.isfinite(arr)
        if bad.any():
            problems.append(f"{name}: {int(bad.sum())} non-finite value(s), first at row {int(np.argmax(bad))}")
    det = cov_ee_m2 * cov_nn_m2 - cov_en_m2 ** 2
    not_psd = (cov_ee_m2 < -tol_m2) | (cov_nn_m2 < -tol_m2) | (det < -tol_m2)
    if not_psd.any():
        r = int(np.argmax(not_psd))
        problems.append(f"covariance not positive semi-definite in {int(not_psd.sum())} row(s); first row {r}: "
                        f"[[{cov_ee_m2[r]:.3g}, {cov_en_m2[r]:.3g}], [{cov_en_m2[r]:.3g}, {cov_nn_m2[r]:.3g}]] m^2")
    uniq, counts = np.unique(corner_id, return_counts=True)
    if (counts > 1).any():
        problems.append(f"corner_id not unique: {int((counts > 1).sum())} duplicated id(s), e.g. "
                        f"{int(uniq[np.argmax(counts > 1)])}")
    return problems


def evaluate_gates(n_corners: int, driven_m: float, corner_tiles: set[tuple[int, int]],
                   driven_tiles: set[tuple[int, int]], min_corners_per_km: float,
                   max_empty_path_tile_share: float) -> tuple[dict[str, float], list[str]]:
    """(measured values, failures) of the density gates. A map with no driven path fails."""
    km = driven_m / 1000.0
    per_km = n_corners / km if km > 0 else 0.0
    empty = driven_tiles - corner_tiles
    share = len(empty) / len(driven_tiles) if driven_tiles else 1.0
    measured = {"driven_km": km, "corners_per_km": per_km, "path_tiles": float(len(driven_tiles)),
                "empty_path_tile_share": share}
    failures = []
    if km <= 0:
        failures.append("no driven path: poses_optimized has fewer than two poses per drive; "
                        "hint: check the posegraph stage output")
    elif per_km < min_corners_per_km:
        failures.append(f"corner density {per_km:.1f} corners/km < min_corners_per_km {min_corners_per_km:g} "
                        f"({n_corners} corners over {km:.3f} km); hint: check the corners/cornermap stages or "
                        "lower the gate")
    if driven_tiles and share > max_empty_path_tile_share:
        sample = ", ".join(f"({i},{j})" for i, j in sorted(empty)[:5])
        failures.append(f"{len(empty)} of {len(driven_tiles)} tiles along the driven path hold no corner "
                        f"(share {share:.2f} > max_empty_path_tile_share {max_empty_path_tile_share:g}); "
                        f"e.g. {sample}")
    return measured, failures
