"""Corner layer vs poses: is the published corner layer in the frame of the optimized poses of every drive?

Every drive's per-scan corners (map drives and reference/evaluation drives alike), placed with that drive's
optimized poses, are matched to the nearest kept map corner; per drive the median offset, the RMS and a rigid 2-D
fit (shift and rotation) of the observations onto their map corners measure how far the layer sits from the frame
the poses define. A localizer on the map is scored against those poses (``map`` reference), so an offset here is
an error no filter can remove. Pure numpy/scipy.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.common.geometry import fit_rigid_2d


def layer_vs_poses(map_en_m: np.ndarray, obs_en_m: np.ndarray, obs_drive_code: np.ndarray, drive_names: list[str],
                   max_match_m: float = 1.0, min_matches: int = 3) -> dict[str, dict]:
    """Per drive: observations within ``max_match_m`` of a map corner, their median offset from it (east, north),
    RMS distance, and the rigid fit moving the observations onto the map corners (rotation about the matched
    observations' centroid, and shift there). Drives with fewer than ``min_matches`` matches report counts only."""
    out: dict[str, dict] = {}
    map_en_m = np.asarray(map_en_m, dtype=float).reshape(-1, 2)
    obs_en_m = np.asarray(obs_en_m, dtype=float).reshape(-1, 2)
    tree = cKDTree(map_en_m) if len(map_en_m) else None
    for code, name in enumerate(drive_names):
        sel = np.flatnonzero(np.asarray(obs_drive_code) == code)
        row: dict = {"n_observations": int(len(sel)), "n_matched": 0}
        if tree is not None and len(sel):
            d, idx = tree.query(obs_en_m[sel], distance_upper_bound=max_match_m)
            ok = np.isfinite(d)
            row["n_matched"] = int(ok.sum())
            row["n_map_corners_seen"] = int(len(np.unique(idx[ok])))
            if ok.sum() >= min_matches and row["n_map_corners_seen"] >= 2:
                src, dst = obs_en_m[sel][ok], map_en_m[idx[ok]]
                off = src - dst
                R, t = fit_rigid_2d(src, dst)
                c = src.mean(axis=0)
                row.update({"median_offset_en_m": [float(np.median(off[:, 0])), float(np.median(off[:, 1]))],
                            "rms_m": float(np.sqrt(np.mean(np.sum(off**2, axis=1)))),
                            "fit_shift_m": float(np.hypot(*(R @ c + t - c))),
                            "fit_rotation_deg": float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))})
        out[name] = row
    return out
