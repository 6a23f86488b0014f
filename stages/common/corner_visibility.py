"""Which map corners a vehicle at a point can see: range, the side of the walls, and the other buildings' walls.

A corner is the meeting of two walls whose directions from the corner are ``theta1_rad`` and ``theta2_rad``; the
corners stage finds it only where both walls are seen (``stages/corners/candidates.py``). ``convex`` (an outside
building corner) means the sensor that found it lay outside the wedge between the walls: both walls' outer faces
are then seen only from the opposite wedge; an inside corner (``convex`` false) is seen from within its own wedge.
A point sees a corner when it lies within ``range_m``, inside that region by at least ``min_incidence_rad`` off
each wall's line (a wall seen at a grazing angle gives no line), and no mapped wall crosses the line of sight.

Walls are not stored in the map; they are rebuilt from its corners: the wall leaving a corner along one of its
directions ends at the nearest corner lying along it (within ``pair_tol_rad``) whose own wall points back, else it
is a stub of ``stub_m``. Pure numpy; arrays in, arrays out.
"""
from __future__ import annotations

import numpy as np


def _unit(theta_rad: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(theta_rad), np.sin(theta_rad)], axis=-1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def side_visible(points_en_m: np.ndarray, corners_en_m: np.ndarray, theta_rad: np.ndarray, convex: np.ndarray,
                 min_incidence_rad: float) -> np.ndarray:
    """(N, K) True where point n lies where corner k's two walls are both seen (see the module doc)."""
    p = np.asarray(points_en_m, float).reshape(-1, 2)
    c = np.asarray(corners_en_m, float).reshape(-1, 2)
    u1, u2 = _unit(np.asarray(theta_rad, float)[:, 0]), _unit(np.asarray(theta_rad, float)[:, 1])
    d = p[:, None, :] - c[None, :, :]
    dist = np.maximum(np.linalg.norm(d, axis=2), 1e-9)
    # the side of wall 1's line holding wall 2 (and vice versa): +1 / -1 per corner
    s1, s2 = np.sign(_cross(u1, u2)), np.sign(_cross(u2, u1))
    inside_wedge = (s1 * _cross(u1[None], d) > 0) & (s2 * _cross(u2[None], d) > 0)
    # the opposite wedge: on the far side of both lines
    opposite = (s1 * _cross(u1[None], d) < 0) & (s2 * _cross(u2[None], d) < 0)
    region = np.where(np.asarray(convex, bool)[None, :], opposite, inside_wedge)
    margin = np.sin(min_incidence_rad) * dist
    clear = (np.abs(_cross(u1[None], d)) >= margin) & (np.abs(_cross(u2[None], d)) >= margin)
    return region & clear


def wall_segments(corners_en_m: np.ndarray, theta_rad: np.ndarray, *, max_len_m: float = 80.0,
                  pair_tol_rad: float = np.deg2rad(5.0), stub_m: float = 5.0) -> np.ndarray:
    """(S, 2, 2) wall segments rebuilt from the corners, each wall once (see the module doc)."""
    c = np.asarray(corners_en_m, float).reshape(-1, 2)
    th = np.asarray(theta_rad, float).reshape(-1, 2)
    k = len(c)
    if k == 0:
        return np.zeros((0, 2, 2))
    segs, seen = [], set()
    d = c[None, :, :] - c[:, None, :]  # d[i, j] = c_j - c_i
    dist = np.linalg.norm(d, axis=2)
    bearing = np.arctan2(d[..., 1], d[..., 0])
    for i in range(k):
        for w in range(2):
            ang = np.abs((bearing[i] - th[i, w] + np.pi) % (2 * np.pi) - np.pi)
            back = np.min(np.abs((th - th[i, w]) % (2 * np.pi) - np.pi), axis=1)  # a wall of j pointing back
            ok = (ang <= pair_tol_rad) & (dist[i] > 0.5) & (dist[i] <= max_len_m) & (back <= 2 * pair_tol_rad)
            ok[i] = False
            if ok.any():
                j = int(np.flatnonzero(ok)[np.argmin(dist[i][ok])])
                key = (min(i, j), max(i, j))
                if key not in seen:
                    seen.add(key)
                    segs.append((c[i], c[j]))
            else:
                segs.append((c[i], c[i] + stub_m * _unit(th[i, w])))
    return np.asarray(segs, float).reshape(-1, 2, 2)


def occluded(points_en_m: np.ndarray, corners_en_m: np.ndarray, segments: np.ndarray,
             end_gap_m: float = 0.3) -> np.ndarray:
    """(N, K) True where a wall segment crosses the line of sight from point n to corner k (the last
    ``end_gap_m`` before the corner excluded: its own walls meet there)."""
    p = np.asarray(points_en_m, float).reshape(-1, 2)
    c = np.asarray(corners_en_m, float).reshape(-1, 2)
    out = np.zeros((len(p), len(c)), bool)
    if len(segments) == 0 or len(p) == 0 or len(c) == 0:
        return out
    a, b = segments[:, 0], segments[:, 1]  # (S, 2)
    for n in range(len(p)):
        v = c - p[n]
        length = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
        q = c - v / length * np.minimum(end_gap_m, 0.5 * length)  # sight line p -> q, (K, 2)
        r = q - p[n]
        s = b - a
        denom = _cross(r[:, None, :], s[None, :, :])  # (K, S)
        ap = a[None, :, :] - p[n]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _cross(ap, s[None, :, :]) / denom
            u = _cross(ap, r[:, None, :]) / denom
        hit = (np.abs(denom) > 1e-12) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)
        out[n] = hit.any(axis=1)
    return out


def visible(points_en_m: np.ndarray, corners_en_m: np.ndarray, theta_rad: np.ndarray, convex: np.ndarray, *,
            range_m: float, min_incidence_rad: float = np.deg2rad(10.0), segments: np.ndarray | None = None
            ) -> np.ndarray:
    """(N, K) True where point n sees corner k: in range, on the walls' seen side, not behind a mapped wall."""
    p = np.asarray(points_en_m, float).reshape(-1, 2)
    c = np.asarray(corners_en_m, float).reshape(-1, 2)
    near = np.linalg.norm(p[:, None, :] - c[None, :, :], axis=2) <= range_m
    out = near & side_visible(p, c, theta_rad, convex, min_incidence_rad)
    if segments is not None and out.any():
        rows = np.flatnonzero(out.any(axis=1))
        cols = np.flatnonzero(out.any(axis=0))
        blocked = occluded(p[rows], c[cols], segments)
        sub = out[np.ix_(rows, cols)] & ~blocked
        out[np.ix_(rows, cols)] = sub
    return out
