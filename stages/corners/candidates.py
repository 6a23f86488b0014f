"""Corner candidates from pairs of neighbouring lines of one ring (Im et al. 2016 s.2.2.3), with covariance.

Covariance model: each TLS line is perturbed by a rotation about its centroid (var sigma^2 / spread) and a shift
along its normal (var sigma^2 / n), uncorrelated at the centroid. With n_i . p = offset_i for both lines,
n_i . dp = d_offset_i - s_i d_alpha_i where s_i is the signed distance from line i's centroid to the corner along
the line, so Cov(p) = A^-1 diag(var_1, var_2) A^-T, A = [n_1; n_2]. A near-flat corner (A nearly singular) gets
the large, elongated uncertainty of the paper's Figure 26.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from stages.corners.lines import LineSegments


@dataclass(frozen=True)
class CornerCandidates:
    """M single-layer candidates in the sensor frame. theta1 points from the corner along the wall seen first
    (lower azimuth, the ring runs counter-clockwise), theta2 along the wall seen second."""

    x_m: np.ndarray
    y_m: np.ndarray
    theta1_rad: np.ndarray
    theta2_rad: np.ndarray
    cov_m2: np.ndarray  # (M, 2, 2)
    layer: np.ndarray
    interior_angle_rad: np.ndarray  # angle between the two wall directions, in (0, pi)
    convex: np.ndarray  # True: the sensor lies outside the wedge between the walls (an outside building corner)
    line_a: np.ndarray  # index of the first line in the LineSegments given
    line_b: np.ndarray
    # vertex support: the smaller of the two facing-end gaps (end point to intersection), each in point spacings of
    # its own line (length / (points - 1)); a line that reaches a sharp vertex ends within about one spacing of it
    vertex_gap_spacings: np.ndarray

    def __len__(self) -> int:
        return int(self.x_m.size)

    def take(self, index: np.ndarray) -> "CornerCandidates":
        return CornerCandidates(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def find_corner_candidates(lines: LineSegments, xy_m: np.ndarray, *, max_corner_gap_m: float,
                           min_interior_angle_rad: float, max_interior_angle_rad: float, line_sigma_floor_m: float,
                           ) -> CornerCandidates:
    """Candidates from consecutive lines of the same ring (``lines`` sorted by start index, outliers removed).

    Kept when the two lines' intersection lies within ``max_corner_gap_m`` of the facing end point of each line
    and the angle between the walls is inside [min_interior_angle_rad, max_interior_angle_rad].
    Each line's residual sigma is floored at ``line_sigma_floor_m`` before propagation.
    """
    k = len(lines)
    ia = np.arange(max(k - 1, 0))
    ia = ia[lines.layer[ia] == lines.layer[ia + 1]] if k > 1 else ia
    ib = ia + 1
    na = np.column_stack([np.cos(lines.normal_rad[ia]), np.sin(lines.normal_rad[ia])])
    nb = np.column_stack([np.cos(lines.normal_rad[ib]), np.sin(lines.normal_rad[ib])])
    det = _cross(na, nb)
    ok = np.abs(det) > 1e-6
    ia, ib, na, nb, det = ia[ok], ib[ok], na[ok], nb[ok], det[ok]
    ra, rb = lines.offset_m[ia], lines.offset_m[ib]
    px = (ra * nb[:, 1] - rb * na[:, 1]) / det
    py = (rb * na[:, 0] - ra * nb[:, 0]) / det
    p = np.column_stack([px, py])
    gap_a = np.hypot(*(xy_m[lines.stop[ia]] - p).T)
    gap_b = np.hypot(*(xy_m[lines.start[ib]] - p).T)
    # wall directions from the corner, towards each line's centroid
    ta = np.column_stack([-na[:, 1], na[:, 0]])
    tb = np.column_stack([-nb[:, 1], nb[:, 0]])
    sa = np.einsum("ij,ij->i", p - lines.centroid_xy_m[ia], ta)  # corner position along line a from its centroid
    sb = np.einsum("ij,ij->i", p - lines.centroid_xy_m[ib], tb)
    ua = -np.sign(sa)[:, None] * ta
    ub = -np.sign(sb)[:, None] * tb
    interior = np.arccos(np.clip(np.einsum("ij,ij->i", ua, ub), -1.0, 1.0))
    spacing_a = lines.length_m[ia] / np.maximum(lines.n_points[ia] - 1, 1)
    spacing_b = lines.length_m[ib] / np.maximum(lines.n_points[ib] - 1, 1)
    vertex_gap = np.minimum(gap_a / np.maximum(spacing_a, 1e-9), gap_b / np.maximum(spacing_b, 1e-9))
    keep = ((gap_a <= max_corner_gap_m) & (gap_b <= max_corner_gap_m) & (interior >= min_interior_angle_rad)
            & (interior <= max_interior_angle_rad) & (sa != 0) & (sb != 0))
    ia, ib, p, ua, ub, interior, det = ia[keep], ib[keep], p[keep], ua[keep], ub[keep], interior[keep], det[keep]
    vertex_gap = vertex_gap[keep]
    na, nb, sa, sb = na[keep], nb[keep], sa[keep], sb[keep]
    # covariance propagated from the two TLS fits
    floor2 = line_sigma_floor_m ** 2
    var_lines = []
    for i, s in ((ia, sa), (ib, sb)):
        n_pts = lines.n_points[i].astype(float)
        sigma2 = np.maximum(lines.residual_var_m2[i] * n_pts / np.maximum(n_pts - 2.0, 1.0), floor2)
        var_lines.append(sigma2 / n_pts + s * s * sigma2 / np.maximum(lines.spread_m2[i], 1e-12))
    a_inv = np.empty((ia.size, 2, 2))
    a_inv[:, 0, 0], a_inv[:, 0, 1] = nb[:, 1] / det, -na[:, 1] / det
    a_inv[:, 1, 0], a_inv[:, 1, 1] = -nb[:, 0] / det, na[:, 0] / det
    cov = np.einsum("mik,mk,mjk->mij", a_inv, np.column_stack(var_lines), a_inv)
    # convex: the sensor (origin) is outside the wedge spanned by the two wall directions
    v = -p
    c_ab = _cross(ua, ub)
    inside = (_cross(ua, v) * c_ab > 0) & (_cross(v, ub) * c_ab > 0)
    return CornerCandidates(x_m=p[:, 0], y_m=p[:, 1], theta1_rad=np.arctan2(ua[:, 1], ua[:, 0]),
                            theta2_rad=np.arctan2(ub[:, 1], ub[:, 0]), cov_m2=cov, layer=lines.layer[ia],
                            interior_angle_rad=interior, convex=~inside, line_a=ia, line_b=ib,
                            vertex_gap_spacings=vertex_gap)
