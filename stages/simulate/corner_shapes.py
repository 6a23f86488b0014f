"""Rounded and chamfered building corners. A share of the convex footprint vertices is replaced in the
building's *outline* (what the mesh and the survey use) by a circular arc of radius U(``radius_m``) tangent
to both walls, or by a straight cut ``U(chamfer_m)`` back from the vertex along each wall. The footprint keeps
the sharp vertex: it is the walls' intersection, which ``truth/corners.csv`` lists with the corner's shape.

An arc or a cut takes at most 35 % of either wall; vertices within 1 m of another building (party walls)
stay sharp. Arc and cut segments are glass only when both walls are.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.simulate.geom2d import point_segment_distance_m

SHARP, ROUNDED, CHAMFERED = 0, 1, 2
SHAPE_NAMES = ("sharp", "rounded", "chamfered")
ARC_STEP_M = 0.3  # arc facet length in the mesh
MAX_WALL_SHARE = 0.35
NEAR_OTHER_M = 1.0


def shape_corners(buildings: list, rounded_share: float, chamfered_share: float, radius_m: tuple[float, float],
                  chamfer_m: tuple[float, float], rng: np.random.Generator) -> list:
    """Buildings with ``outline_en``/``outline_glass``/``corner_shape``/``shape_size_m`` set."""
    lo = np.array([b.footprint_en.min(axis=0) for b in buildings]).reshape(-1, 2) - NEAR_OTHER_M
    hi = np.array([b.footprint_en.max(axis=0) for b in buildings]).reshape(-1, 2) + NEAR_OTHER_M
    out = []
    for i, b in enumerate(buildings):
        fp = b.footprint_en
        n = len(fp)
        draw = rng.random(n)
        size = np.where(draw < rounded_share, rng.uniform(*radius_m, n), rng.uniform(*chamfer_m, n))
        shape = np.where(draw < rounded_share, ROUNDED,
                         np.where(draw < rounded_share + chamfered_share, CHAMFERED, SHARP))
        others = [j for j in range(len(buildings)) if j != i and np.all(lo[j] <= hi[i]) and np.all(lo[i] <= hi[j])]
        for k in np.flatnonzero(shape != SHARP):
            tangent = _tangent_length_m(fp, k, shape[k], size[k])
            if tangent is None or _near_other(fp[k], [buildings[j].footprint_en for j in others]):
                shape[k] = SHARP
        size = np.where(shape == SHARP, 0.0, size)
        outline, glass = shaped_outline(fp, b.glass, shape, size)
        out.append(replace(b, outline_en=outline, outline_glass=glass, corner_shape=shape, shape_size_m=size))
    return out


def _turn_rad(fp: np.ndarray, k: int) -> float:
    d_in = fp[k] - fp[k - 1]
    d_out = fp[(k + 1) % len(fp)] - fp[k]
    return float(np.arctan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], d_in @ d_out))


def _tangent_length_m(fp: np.ndarray, k: int, shape: int, size: float) -> float | None:
    """Distance from the vertex to where the arc/cut meets each wall, or None if the vertex can't take it."""
    turn = _turn_rad(fp, k)
    if not np.radians(20.0) < turn < np.radians(150.0):  # convex (left turn, ccw footprint), not a sliver
        return None
    tangent = size * np.tan(turn / 2.0) if shape == ROUNDED else size
    walls = min(np.linalg.norm(fp[k] - fp[k - 1]), np.linalg.norm(fp[(k + 1) % len(fp)] - fp[k]))
    return tangent if tangent <= MAX_WALL_SHARE * walls else None


def _near_other(v: np.ndarray, polys: list[np.ndarray]) -> bool:
    return any(point_segment_distance_m(v, q[m], q[(m + 1) % len(q)]) < NEAR_OTHER_M
               for q in polys for m in range(len(q)))


def shaped_outline(fp: np.ndarray, glass: np.ndarray, shape: np.ndarray, size: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Footprint (n, 2) ccw with per-wall glass (wall k from vertex k to k+1) -> outline (m, 2) ccw and its
    per-segment glass, with arcs (radius ``size``) or cuts (``size`` back along each wall) at shaped vertices."""
    pts, seg_glass = [], []
    n = len(fp)
    for k in range(n):
        if shape[k] == SHARP:
            pts.append(fp[k])
            seg_glass.append(bool(glass[k]))
            continue
        d_in = (fp[k] - fp[k - 1]) / np.linalg.norm(fp[k] - fp[k - 1])
        d_out = (fp[(k + 1) % n] - fp[k]) / np.linalg.norm(fp[(k + 1) % n] - fp[k])
        turn = _turn_rad(fp, k)
        both = bool(glass[k - 1] and glass[k])
        if shape[k] == CHAMFERED:
            piece = [fp[k] - d_in * size[k], fp[k] + d_out * size[k]]
        else:
            a = fp[k] - d_in * size[k] * np.tan(turn / 2.0)
            centre = a + np.array([-d_in[1], d_in[0]]) * size[k]
            start = np.arctan2(*(a - centre)[::-1])
            m = max(2, int(np.ceil(turn * size[k] / ARC_STEP_M)))
            ang = start + np.linspace(0.0, turn, m + 1)
            piece = list(centre + size[k] * np.column_stack([np.cos(ang), np.sin(ang)]))
        pts += piece
        seg_glass += [both] * (len(piece) - 1) + [bool(glass[k])]
    return np.asarray(pts, float), np.asarray(seg_glass, bool)
