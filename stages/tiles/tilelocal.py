"""Tile-local re-derivation: which tiles of a new map version are *touched* and which keep the parent's files.

The corner map, the marking rasters and the localizability layer are derived for the whole map; a tile the new
version does not touch then keeps its parent's files byte for byte (same sha256; docs/maintenance.md, "Tiles of an
incremental rebuild"). A tile present in both versions is **touched** when any of these holds:

1. *corners*: a corner of the tile (in either version; matched by id) was added or removed, moved to another
   tile, got an observation more or fewer (``n_obs``, ``n_drives``, ``drives``: a new drive saw it), moved more than
   ``corner_tol_m`` or its covariance changed by more than ``cov_tol_rel`` (Frobenius norm, relative). A cluster
   straddling a border that changes touches both tiles (its id leaves one and enters the other).
2. *paths*: a pose that is new (a new drive's; or one the new version no longer holds) or moved by more than
   ``pose_tol_m`` lies in the tile (the localizability layer samples the map drives' paths). A pose moves by
   ``|dt| + pose_reach_m |dtheta|``: the largest displacement of a point it sees ``pose_reach_m`` away.
3. *rasters*: its marking raster files would get other bytes (a new survey, or rasters painted from drives whose
   scans moved), or a neighbour's would (the vector markings read the neighbours' masks near the border).

Pure numpy: arrays in, sets of tile keys out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.tiling import tile_key_of


@dataclass(frozen=True)
class CornerSet:
    """One version's corners as arrays (any row order)."""

    ids: np.ndarray  # (K,) int64
    en_m: np.ndarray  # (K,2)
    cov_m2: np.ndarray  # (K,3) cov_ee, cov_en, cov_nn
    n_obs: np.ndarray  # (K,) int
    drives: list  # (K,) the drives that saw each corner (any comparable value)


@dataclass(frozen=True)
class Tolerances:
    corner_tol_m: float
    cov_tol_rel: float
    pose_tol_m: float
    pose_reach_m: float


def corner_changed_tiles(
    prev: CornerSet, new: CornerSet, size_m: float, tol: Tolerances
) -> tuple[set[tuple[int, int]], np.ndarray]:
    """(tiles touched by rule 1, (M,) displacement in metres of the new corners whose id the parent holds in the
    same tile without any other change, the shift a kept tile leaves unpublished; NaN for the others)."""
    pi, pj = tile_key_of(prev.en_m[:, 0], prev.en_m[:, 1], size_m) if len(prev.ids) else (np.zeros(0, int),) * 2
    ni, nj = tile_key_of(new.en_m[:, 0], new.en_m[:, 1], size_m) if len(new.ids) else (np.zeros(0, int),) * 2
    row_of_prev = {int(c): r for r, c in enumerate(prev.ids.tolist())}
    touched: set[tuple[int, int]] = set()
    shift = np.full(len(new.ids), np.nan)
    seen = set()
    for r, cid in enumerate(new.ids.tolist()):
        key = (int(ni[r]), int(nj[r]))
        p = row_of_prev.get(int(cid))
        if p is None:
            touched.add(key)
            continue
        seen.add(int(cid))
        pkey = (int(pi[p]), int(pj[p]))
        if pkey != key:
            touched.update((key, pkey))
            continue
        d = float(np.hypot(*(new.en_m[r] - prev.en_m[p])))
        c_new, c_prev = new.cov_m2[r], prev.cov_m2[p]
        cov_rel = float(np.linalg.norm(_full(c_new) - _full(c_prev)) / max(np.linalg.norm(_full(c_prev)), 1e-30))
        if (
            d > tol.corner_tol_m
            or cov_rel > tol.cov_tol_rel
            or int(new.n_obs[r]) != int(prev.n_obs[p])
            or _drives(new.drives[r]) != _drives(prev.drives[p])
        ):
            touched.add(key)
        else:
            shift[r] = d
    for p, cid in enumerate(prev.ids.tolist()):
        if int(cid) not in seen:
            touched.add((int(pi[p]), int(pj[p])))
    return touched, shift


def _full(c: np.ndarray) -> np.ndarray:
    return np.array([[c[0], c[1]], [c[1], c[2]]], float)


def _drives(value) -> tuple:
    return tuple(sorted(value)) if isinstance(value, (list, tuple, np.ndarray)) else (value,)


def changed_poses(
    prev: dict[str, tuple[np.ndarray, np.ndarray]], new: dict[str, tuple[np.ndarray, np.ndarray]], tol: Tolerances
) -> tuple[np.ndarray, dict[str, float]]:
    """((N,2) positions of the poses that are new, gone or moved beyond ``pose_tol_m`` (moved: ``|dt| + reach
    |dtheta|``, the rotation angle between the two orientations), {drive: its largest such displacement of a pose
    kept within the tolerance}). ``prev`` / ``new``: drive -> (stamp_ns (N,), x y z qx qy qz qw (N,7))."""
    out = []
    within: dict[str, float] = {}
    for drive in sorted(set(prev) | set(new)):
        if drive not in new:
            out.append(prev[drive][1][:, :2])
            continue
        stamps, poses = new[drive]
        if drive not in prev:
            out.append(poses[:, :2])
            continue
        p_stamps, p_poses = prev[drive]
        order = np.argsort(p_stamps, kind="stable")
        pos = np.clip(np.searchsorted(p_stamps[order], stamps), 0, max(len(order) - 1, 0))
        hit = (p_stamps[order][pos] == stamps) if len(order) else np.zeros(len(stamps), bool)
        moved = np.full(len(stamps), np.inf)
        if hit.any():
            a, b = poses[hit], p_poses[order][pos[hit]]
            dt = np.linalg.norm(a[:, :3] - b[:, :3], axis=1)
            dot = np.clip(
                np.abs(np.sum(a[:, 3:7] * b[:, 3:7], axis=1))
                / np.maximum(np.linalg.norm(a[:, 3:7], axis=1) * np.linalg.norm(b[:, 3:7], axis=1), 1e-300),
                0.0,
                1.0,
            )
            moved[hit] = dt + tol.pose_reach_m * 2.0 * np.arccos(dot)
        bad = moved > tol.pose_tol_m
        out.append(poses[bad, :2])
        gone = np.setdiff1d(p_stamps, stamps)  # poses the new version no longer holds
        if len(gone):
            out.append(p_poses[np.isin(p_stamps, gone), :2])
        within[drive] = float(moved[~bad].max()) if (~bad).any() else 0.0
    pts = np.vstack(out) if out else np.zeros((0, 2))
    return pts, within


def tiles_of(points_en_m: np.ndarray, size_m: float) -> set[tuple[int, int]]:
    """Tiles holding the points."""
    if len(points_en_m) == 0:
        return set()
    i, j = tile_key_of(points_en_m[:, 0], points_en_m[:, 1], size_m)
    return set(zip(i.tolist(), j.tolist()))
