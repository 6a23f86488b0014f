"""The evaluation drive on the map's previous version: errors of both versions and the corners that changed.

When the published version names a ``parent_version``, the EKF runs again on that version with the same drive
arrays and references, and the corners near the drive are matched between the two versions (mutual nearest
neighbours within ``match_radius_m``): unmatched current corners were added, unmatched previous ones removed,
matched ones farther apart than ``moved_m`` moved. The report draws them on the map and puts both versions'
errors side by side.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CornerChanges:
    added: np.ndarray  # indices into the current corners
    removed: np.ndarray  # indices into the previous corners
    moved: np.ndarray  # indices into the current corners (matched, farther than moved_m)
    moved_by_m: np.ndarray  # (len(moved),)


def match_corners(current_en_m: np.ndarray, previous_en_m: np.ndarray, match_radius_m: float = 1.0,
                  moved_m: float = 0.1) -> CornerChanges:
    """Mutual nearest neighbours within ``match_radius_m`` between two corner sets (K,2) and (L,2)."""
    from scipy.spatial import cKDTree

    cur, prev = np.asarray(current_en_m, float).reshape(-1, 2), np.asarray(previous_en_m, float).reshape(-1, 2)
    empty = np.zeros(0, np.int64)
    if len(cur) == 0 or len(prev) == 0:
        return CornerChanges(np.arange(len(cur)), np.arange(len(prev)), empty, np.zeros(0))
    d_cp, j = cKDTree(prev).query(cur, distance_upper_bound=match_radius_m)
    _, i_back = cKDTree(cur).query(prev, distance_upper_bound=match_radius_m)
    ok = np.isfinite(d_cp)
    ok[ok] &= i_back[j[ok]] == np.flatnonzero(ok)
    matched_prev = np.zeros(len(prev), bool)
    matched_prev[j[ok]] = True
    moved = np.flatnonzero(ok & (d_cp > moved_m))
    return CornerChanges(np.flatnonzero(~ok), np.flatnonzero(~matched_prev), moved, d_cp[moved])


def previous_version(reader):
    """A reader of the version this one was built on (``parent_version`` in its manifest), or None."""
    from mapformat.loader import open_map  # the public consumer API (see compute's module doc)
    from pipeline.errors import CornermapError

    parent = reader.manifest.get("parent_version")
    if parent is None:
        return None
    try:
        return open_map(reader.path.parent, int(parent))
    except CornermapError as exc:
        log.warning("map %s names parent version %s, which cannot be opened (%s): no version comparison",
                    reader.path, parent, exc)
        return None


def comparison_document(version: int, prev_version: int, cmap, prev_cmap, metrics_cur: dict, metrics_prev: dict,
                        reference: str | None, match_radius_m: float = 1.0, moved_m: float = 0.1) -> dict:
    """The ``comparison`` entry of metrics.json (corner coordinates included for the report's figure)."""
    ch = match_corners(cmap.en_m, prev_cmap.en_m, match_radius_m, moved_m)
    ekf = {"current": (metrics_cur.get("ekf") or {}).get(reference),
           "previous": (metrics_prev.get("ekf") or {}).get(reference)}
    return {"current_version": int(version), "previous_version": int(prev_version), "methods": ["ekf"],
            "reference": reference, "match_radius_m": match_radius_m, "moved_threshold_m": moved_m,
            "corners_near_drive": {"current": int(len(cmap.en_m)), "previous": int(len(prev_cmap.en_m))},
            "added": int(len(ch.added)), "removed": int(len(ch.removed)), "moved": int(len(ch.moved)),
            "added_en_m": np.round(cmap.en_m[ch.added], 3).tolist(),
            "removed_en_m": np.round(prev_cmap.en_m[ch.removed], 3).tolist(),
            "moved_en_m": np.round(cmap.en_m[ch.moved], 3).tolist(),
            "moved_by_m": np.round(ch.moved_by_m, 4).tolist(), "ekf": ekf}
