"""Small planar geometry helpers for the city generator (ENU east/north metres, polygons counter-clockwise)."""
from __future__ import annotations

import numpy as np


def signed_area_m2(poly_en: np.ndarray) -> float:
    x, y = poly_en[:, 0], poly_en[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def intersect_lines(p1: np.ndarray, d1: np.ndarray, p2: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Intersection of lines p1 + s d1 and p2 + t d2 (falls back to the midpoint for parallel lines)."""
    cross = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(cross) < 1e-9:
        return 0.5 * (p1 + p2)
    s = ((p2[0] - p1[0]) * d2[1] - (p2[1] - p1[1]) * d2[0]) / cross
    return p1 + s * d1


def offset_polygon_inward(poly_en: np.ndarray, dist_m: np.ndarray | float) -> np.ndarray:
    """Move every edge of a convex CCW polygon inward by ``dist_m`` (per edge), re-intersecting neighbours."""
    n = len(poly_en)
    dist = np.broadcast_to(np.asarray(dist_m, float), (n,))
    d = np.roll(poly_en, -1, axis=0) - poly_en
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    left = np.column_stack([-d[:, 1], d[:, 0]])  # interior side of a CCW polygon
    p = poly_en + left * dist[:, None]
    return np.array([intersect_lines(p[k - 1], d[k - 1], p[k], d[k]) for k in range(n)])


def bilinear(quad_en: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Map unit-square points (u, v) into a quad (p00, p10, p11, p01), counter-clockwise."""
    u, v = uv[:, :1], uv[:, 1:2]
    p00, p10, p11, p01 = quad_en
    return (1 - u) * (1 - v) * p00 + u * (1 - v) * p10 + u * v * p11 + (1 - u) * v * p01


def triangulate_polygon(poly_en: np.ndarray) -> np.ndarray:
    """Ear clipping of a simple CCW polygon -> (n-2, 3) vertex indices. O(n^3), meant for small footprints."""
    idx = list(range(len(poly_en)))
    tris: list[tuple[int, int, int]] = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(poly_en) ** 2:
        guard += 1
        for k in range(len(idx)):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            pa, pb, pc = poly_en[a], poly_en[b], poly_en[c]
            if (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pb[1] - pa[1]) * (pc[0] - pa[0]) <= 1e-12:
                continue  # reflex or degenerate vertex: not an ear
            others = [j for j in idx if j not in (a, b, c)]
            if others and np.any(points_in_triangle(poly_en[others], pa, pb, pc)):
                continue
            tris.append((a, b, c))
            idx.pop(k)
            break
    tris.append(tuple(idx))  # type: ignore[arg-type]
    return np.array(tris, dtype=np.int64)


def points_in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    def side(p1, p2):
        return (p2[0] - p1[0]) * (p[:, 1] - p1[1]) - (p2[1] - p1[1]) * (p[:, 0] - p1[0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return (s1 >= 0) & (s2 >= 0) & (s3 >= 0)


def polygon_corners(poly_en: np.ndarray) -> np.ndarray:
    """Per vertex of a CCW polygon: theta1, theta2 (rad, ENU ccw from east; directions of the corner lines
    towards the previous and next vertex) and the interior angle (rad, 0..2pi)."""
    to_prev = np.roll(poly_en, 1, axis=0) - poly_en
    to_next = np.roll(poly_en, -1, axis=0) - poly_en
    th1 = np.arctan2(to_prev[:, 1], to_prev[:, 0])
    th2 = np.arctan2(to_next[:, 1], to_next[:, 0])
    interior = (th1 - th2) % (2 * np.pi)  # the interior lies counter-clockwise from the next edge
    return np.column_stack([th1, th2, interior])


def point_segment_distance_m(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from point ``p`` to the segment a-b."""
    seg = b - a
    t = np.clip((p - a) @ seg / (seg @ seg), 0.0, 1.0)
    return float(np.linalg.norm(a + t * seg - p))


def point_in_polygon(p: np.ndarray, poly_en: np.ndarray) -> np.ndarray:
    """Even-odd rule, vectorised over points."""
    inside = np.zeros(len(p), bool)
    x, y = p[:, 0], p[:, 1]
    for k in range(len(poly_en)):
        (x1, y1), (x2, y2) = poly_en[k - 1], poly_en[k]
        cond = (y1 > y) != (y2 > y)
        xin = (x2 - x1) * (y - y1) / np.where(y2 == y1, 1e-12, y2 - y1) + x1
        inside ^= cond & (x < xin)
    return inside
