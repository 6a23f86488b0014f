"""Per-type precision / recall of vector road markings against truth geometry (pure).

Lines (lane_solid, lane_dashed, stop_line) are compared as sampled centrelines: precision = share of predicted
samples (every ``step_m``) within ``tol_m`` of a truth line of the same type, recall = share of truth samples
within ``tol_m`` of a predicted line of that type. Polygons (crosswalk, arrow) are compared as objects: a
prediction matches when its centroid lies inside (or within ``tol_m`` of) a truth polygon of its type, a truth
polygon is found when a prediction's centroid does. ``observed`` restricts the truth to what the map saw (a
function of (N, 2) ENU points -> bool), so that streets never driven do not count as misses.
"""
from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from stages.common.marking_vectors import LINE_TYPES, POLYGON_TYPES, TYPES


def sample_polyline(xy_m: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` along a polyline (vertices included), (N, 2)."""
    xy_m = np.asarray(xy_m, float)
    out = [xy_m[:1]]
    for a, b in zip(xy_m[:-1], xy_m[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_m)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def _near(points: np.ndarray, lines: list[np.ndarray], tol_m: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    if not len(points):
        return np.zeros(0, bool)
    if not lines:
        return np.zeros(len(points), bool)
    dense = np.vstack([sample_polyline(xy, tol_m / 10.0) for xy in lines])
    dist, _ = cKDTree(dense).query(points, distance_upper_bound=tol_m * 1.2)
    return dist <= tol_m * 1.05  # the dense sampling's chord error is below tol / 20


def _inside(point: np.ndarray, ring: np.ndarray, tol_m: float) -> bool:
    import cv2

    d = cv2.pointPolygonTest(np.asarray(ring, np.float32).reshape(-1, 1, 2), (float(point[0]), float(point[1])), True)
    return d >= -tol_m


def score_markings(predicted: Iterable[tuple[str, np.ndarray]], truth: Iterable[tuple[str, np.ndarray]],
                   tol_m: float = 0.3, step_m: float = 0.25,
                   observed: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, dict[str, float]]:
    """type -> {precision, recall, n_predicted, n_truth} (counts: features; NaN when undefined)."""
    pred, true = list(predicted), list(truth)
    out: dict[str, dict[str, float]] = {}
    for kind in TYPES:
        p = [np.asarray(xy, float) for k, xy in pred if k == kind]
        t = [np.asarray(xy, float) for k, xy in true if k == kind]
        if kind in LINE_TYPES:
            ps = np.vstack([sample_polyline(xy, step_m) for xy in p]) if p else np.zeros((0, 2))
            ts = np.vstack([sample_polyline(xy, step_m) for xy in t]) if t else np.zeros((0, 2))
            if observed is not None and len(ts):
                ts = ts[observed(ts)]
                t = [xy for xy in t if observed(sample_polyline(xy, step_m)).any()]
            hp, ht = _near(ps, t, tol_m), _near(ts, p, tol_m)
            prec = float(hp.mean()) if len(hp) else float("nan")
            rec = float(ht.mean()) if len(ht) else float("nan")
        else:
            assert kind in POLYGON_TYPES
            if observed is not None and t:
                t = [xy for xy in t if bool(observed(xy.mean(axis=0, keepdims=True))[0])]
            pc = [xy.mean(axis=0) for xy in p]
            hit_p = [any(_inside(c, ring, tol_m) for ring in t) for c in pc]
            hit_t = [any(_inside(c, ring, tol_m) for c in pc) for ring in t]
            prec = float(np.mean(hit_p)) if hit_p else float("nan")
            rec = float(np.mean(hit_t)) if hit_t else float("nan")
        out[kind] = {"precision": prec, "recall": rec, "n_predicted": len(p), "n_truth": len(t)}
    return out
