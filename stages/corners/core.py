"""One scan in, its vertical corners out (Im et al. 2016 s.2): the whole chain on numpy arrays.

Frames: everything is in the lidar (sensor) frame, x forward, y left, z up; corners are the projection of a
vertical edge onto the sensor's horizontal plane. Motion distortion within a scan is ignored (see layers.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.corners.candidates import CornerCandidates, find_corner_candidates
from stages.corners.determine import Corners, determine_corners
from stages.corners.layers import find_run_starts, order_rings_by_azimuth, select_layers
from stages.corners.lines import LINE, LineSegments, extract_lines, remove_outlier_lines
from stages.corners.params import CornerParams
from stages.corners.short_objects import estimate_layer_elevation_rad, find_passed_over


@dataclass(frozen=True)
class CornerTrace:
    """Every intermediate of one extraction, for figures and debugging (paper Figure 9)."""

    xy_m: np.ndarray  # selected-layer points, ordered by ring and azimuth
    layer: np.ndarray
    layers_used: np.ndarray
    lines: LineSegments  # all lines, before outlier removal
    line_label: np.ndarray  # lines.LINE / OUTLIER_VARIANCE / OUTLIER_SHORT
    candidates: CornerCandidates
    candidate_corner: np.ndarray  # corner index of each candidate, -1 when dropped by the redundancy check
    corners: Corners


def select_scan_layers(points_xyz: np.ndarray, ring: np.ndarray, params: CornerParams | None = None) -> np.ndarray:
    """The upper-layer ring ids of a scan (or of several scans of one sensor concatenated)."""
    p = params or CornerParams()
    return select_layers(points_xyz, ring, mode=p.layers.layer_selection, n_upper_layers=p.layers.n_upper_layers,
                         min_elevation_deg=p.layers.min_elevation_deg, min_range_m=p.layers.min_range_m)


def _select_and_order(pts: np.ndarray, ring: np.ndarray, layers_used: np.ndarray, min_range_m: float,
                      max_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of the used layers within the range window, grouped by layer and ordered by azimuth.

    Returns xy (M, 2) float64, layer (M,), azimuth (M,) and each point's index in the input."""
    lut = np.zeros(max(int(ring.max()) + 1 if ring.size else 0, int(layers_used.max(initial=-1)) + 1), bool)
    lut[layers_used] = True
    sel = np.flatnonzero(lut[ring]) if ring.size else np.zeros(0, np.intp)
    # 1-D gathers (much faster than fancy-indexing rows of an (N, 3) array)
    x = pts[:, 0].take(sel).astype(np.float64)
    y = pts[:, 1].take(sel).astype(np.float64)
    horiz2 = x * x + y * y
    keep = np.flatnonzero((horiz2 >= min_range_m ** 2) & (horiz2 <= max_range_m ** 2))
    x, y, layer = x[keep], y[keep], ring.take(sel[keep])
    az = np.arctan2(y, x)
    order = order_rings_by_azimuth(np.column_stack([x, y]), layer, az)
    return np.column_stack([x[order], y[order]]), layer[order], az[order], sel[keep][order]


def _keep(corners: Corners, corner_of: np.ndarray, drop: np.ndarray) -> tuple[Corners, np.ndarray]:
    """Remove the corners flagged in ``drop`` and re-index the candidates' corner mapping (-1: none)."""
    if not drop.any():
        return corners, corner_of
    new_id = np.where(drop, -1, np.cumsum(~drop) - 1)
    corner_of = np.where(corner_of >= 0, new_id[np.maximum(corner_of, 0)], -1)
    return corners.take(np.flatnonzero(~drop)), corner_of


def wall_lengths_m(corner_of: np.ndarray, length_a_m: np.ndarray, length_b_m: np.ndarray, n_corners: int
                   ) -> np.ndarray:
    """(K, 2) length of each corner's two walls: the longest line any of its layers saw on each side."""
    out = np.zeros((n_corners, 2))
    used = corner_of >= 0
    np.maximum.at(out[:, 0], corner_of[used], length_a_m[used])
    np.maximum.at(out[:, 1], corner_of[used], length_b_m[used])
    return out


def vertex_gaps_spacings(corner_of: np.ndarray, vertex_gap_spacings: np.ndarray, n_corners: int) -> np.ndarray:
    """(K,) each corner's vertex gap: the smallest of its layers' candidates' (in point spacings; inf: none)."""
    out = np.full(n_corners, np.inf)
    used = corner_of >= 0
    np.minimum.at(out, corner_of[used], vertex_gap_spacings[used])
    return out


def _drop_short_walls(corners: Corners, corner_of: np.ndarray, length_a_m: np.ndarray, length_b_m: np.ndarray, *,
                      min_wall_length_m: float, min_long_wall_length_m: float, obtuse_angle_deg: float,
                      min_obtuse_wall_length_m: float) -> tuple[Corners, np.ndarray]:
    """Small-structure check on the walls as the best of a corner's layers saw them. Dropped when
    - the shorter wall is under ``min_wall_length_m`` or the longer one under ``min_long_wall_length_m`` (bus
      shelters, kiosks): a facade corner whose side wall is seen at a grazing angle keeps a long front wall,
      so only the longer wall has to be long;
    - the corner is obtuse (interior angle over ``obtuse_angle_deg``) and its shorter wall is under
      ``min_obtuse_wall_length_m``: the chords the line split cuts a rounded corner into, and the facet of a
      short chamfer, meet their neighbours at obtuse angles; a rounded corner gives no corner."""
    if not len(corners):
        return corners, corner_of
    walls = wall_lengths_m(corner_of, length_a_m, length_b_m, len(corners))
    shorter, longer = walls.min(axis=1), walls.max(axis=1)
    obtuse = corners.interior_angle_rad > np.radians(obtuse_angle_deg)
    return _keep(corners, corner_of, (shorter < min_wall_length_m) | (longer < min_long_wall_length_m)
                 | (obtuse & (shorter < min_obtuse_wall_length_m)))


def _drop_unsupported(corners: Corners, corner_of: np.ndarray, vertex_gap_spacings: np.ndarray, *,
                      max_vertex_gap_spacings: float) -> tuple[Corners, np.ndarray]:
    """Vertex support: a corner is kept when, in at least one of its layers, a line ends within
    ``max_vertex_gap_spacings`` point spacings of the intersection. A sharp vertex is where both walls' returns
    meet; a chord of a rounded corner meeting a straight wall, with the part of the arc between them left out, puts
    the intersection in empty space that neither line reaches."""
    if not len(corners) or max_vertex_gap_spacings <= 0:
        return corners, corner_of
    return _keep(corners, corner_of,
                 vertex_gaps_spacings(corner_of, vertex_gap_spacings, len(corners)) > max_vertex_gap_spacings)


def _drop_unverifiable(corners: Corners, corner_of: np.ndarray, cand_layer: np.ndarray, pts: np.ndarray,
                       xy: np.ndarray, layer: np.ndarray, az: np.ndarray, src: np.ndarray,
                       layers_used: np.ndarray, *, min_corner_range_m: float, max_passover_height_m: float
                       ) -> tuple[Corners, np.ndarray]:
    """Near-corner and short-object checks; returns the kept corners and the re-indexed candidate mapping."""
    if not len(corners):
        return corners, corner_of
    drop = corners.range_m < min_corner_range_m
    if max_passover_height_m > 0:
        layer_ids = np.unique(layers_used)
        layer_elev = estimate_layer_elevation_rad(np.hypot(xy[:, 0], xy[:, 1]), pts[:, 2].take(src), layer,
                                                  layer_ids)
        top = np.full(len(corners), -np.inf)
        used = corner_of >= 0
        np.maximum.at(top, corner_of[used], layer_elev[np.searchsorted(layer_ids, cand_layer[used])])
        drop |= find_passed_over(np.column_stack([corners.x_m, corners.y_m]), top, xy, az, layer, layer_ids,
                                 layer_elev, max_height_m=max_passover_height_m)
    return _keep(corners, corner_of, drop)


def trace_corners(points_xyz: np.ndarray, ring: np.ndarray, params: CornerParams | None = None, *,
                  layers: np.ndarray | None = None, time_offset_s: np.ndarray | None = None) -> CornerTrace:
    """Run the full extraction on one scan and keep every intermediate.

    ``layers``: the ring ids to use, when already known for the sensor (a ring's elevation is a constant, so
    callers processing many scans select them once); by default selected from this scan.
    ``time_offset_s``: per point, its time after the scan start; gives each corner the time it was seen.
    """
    p = params or CornerParams()
    lay, ln, cl, ck = p.layers, p.lines, p.clusters, p.checks
    pts = np.asarray(points_xyz)
    ring = np.asarray(ring).astype(np.intp, copy=False)
    if pts.ndim != 2 or pts.shape[1] < 3 or ring.shape != (pts.shape[0],):
        raise ValueError(f"extract_corners: expected points (N, 3) and ring (N,); got points {pts.shape} and "
                         f"ring {ring.shape}")
    layers_used = select_scan_layers(pts, ring, p) if layers is None else np.asarray(layers, np.intp)
    xy, layer, az, src = _select_and_order(pts, ring, layers_used, lay.min_range_m, lay.max_range_m)
    run_starts = find_run_starts(xy, layer, break_incidence_deg=ln.break_incidence_deg,
                                 range_sigma_m=ln.range_sigma_m, max_azimuth_gap_deg=ln.max_azimuth_gap_deg,
                                 azimuth_rad=az)
    lines = extract_lines(xy, layer, run_starts, split_distance_m=ln.split_distance_m, min_points=ln.min_points,
                          merge_max_angle_rad=np.radians(ln.merge_max_angle_deg), end_trim_points=ln.end_trim_points)
    label = remove_outlier_lines(lines, max_residual_var_m2=ln.max_residual_var_m2, min_points=ln.min_points,
                                 min_length_m=ln.min_length_m)
    good = np.flatnonzero(label == LINE)
    cand = find_corner_candidates(lines.take(good), xy, max_corner_gap_m=p.candidates.max_corner_gap_m,
                                  min_interior_angle_rad=np.radians(p.candidates.min_interior_angle_deg),
                                  max_interior_angle_rad=np.radians(p.candidates.max_interior_angle_deg),
                                  line_sigma_floor_m=cl.min_sigma_m)
    cand = CornerCandidates(**{**cand.__dict__, "line_a": good[cand.line_a], "line_b": good[cand.line_b]})
    cand_t = None
    if time_offset_s is not None:  # the time of a candidate: its two facing end points
        t_s = np.asarray(time_offset_s, np.float64).take(src)
        cand_t = 0.5 * (t_s[lines.stop[cand.line_a]] + t_s[lines.start[cand.line_b]])
    corners, corner_of = determine_corners(cand, cluster_radius_m=cl.cluster_radius_m,
                                           cluster_max_angle_rad=np.radians(cl.cluster_max_angle_deg),
                                           min_layers=cl.min_layers, min_sigma_m=cl.min_sigma_m,
                                           time_offset_s=cand_t, angular_sigma_rad=cl.angular_sigma_mrad * 1e-3)
    corners, corner_of = _drop_short_walls(
        corners, corner_of, lines.length_m[cand.line_a], lines.length_m[cand.line_b],
        min_wall_length_m=ck.min_wall_length_m, min_long_wall_length_m=ck.min_long_wall_length_m,
        obtuse_angle_deg=ck.obtuse_angle_deg, min_obtuse_wall_length_m=ck.min_obtuse_wall_length_m)
    corners, corner_of = _drop_unsupported(corners, corner_of, cand.vertex_gap_spacings,
                                           max_vertex_gap_spacings=ck.max_vertex_gap_spacings)
    corners, corner_of = _drop_unverifiable(corners, corner_of, cand.layer, pts, xy, layer, az, src, layers_used,
                                            min_corner_range_m=ck.min_corner_range_m,
                                            max_passover_height_m=ck.max_passover_height_m)
    return CornerTrace(xy_m=xy, layer=layer, layers_used=layers_used, lines=lines, line_label=label,
                       candidates=cand, candidate_corner=corner_of, corners=corners)


def extract_corners(points_xyz: np.ndarray, ring: np.ndarray, params: CornerParams | None = None, *,
                    layers: np.ndarray | None = None, time_offset_s: np.ndarray | None = None) -> Corners:
    """Vertical corners of one scan: points (N, 3) in the lidar frame and their ring index (0 = lowest beam)."""
    return trace_corners(points_xyz, ring, params, layers=layers, time_offset_s=time_offset_s).corners
