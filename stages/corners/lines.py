"""Line extraction: IEPF split-and-merge on runs of ring points, total-least-squares refit, outlier test.

All rings of a scan are processed together: IEPF runs level by level over every open segment at once (one
vectorised distance-to-chord pass per level), so there is no per-point Python loop.
Lines are kept in normal form n . p = offset_m with n = (cos normal_rad, sin normal_rad).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

LINE, OUTLIER_VARIANCE, OUTLIER_SHORT = 1, 2, 3  # labels of remove_outlier_lines


@dataclass(frozen=True)
class LineSegments:
    """K line segments over points ordered by ring and azimuth; ``start``/``stop`` are inclusive indices."""

    start: np.ndarray
    stop: np.ndarray
    layer: np.ndarray
    normal_rad: np.ndarray
    offset_m: np.ndarray
    centroid_xy_m: np.ndarray  # (K, 2)
    n_points: np.ndarray  # points used by the fit (after end trimming)
    residual_var_m2: np.ndarray  # mean squared perpendicular residual (paper Figure 5 "Var")
    spread_m2: np.ndarray  # sum of squared along-line coordinates about the centroid
    length_m: np.ndarray

    def __len__(self) -> int:
        return int(self.start.size)

    def take(self, index: np.ndarray) -> "LineSegments":
        return LineSegments(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @property
    def direction_xy(self) -> np.ndarray:
        """Unit direction along each line (normal rotated by +90 deg)."""
        return np.column_stack([-np.sin(self.normal_rad), np.cos(self.normal_rad)])


def split_iepf(xy_m: np.ndarray, run_start: np.ndarray, run_stop: np.ndarray, *, split_distance_m: float,
               min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Iterative End Point Fit: split every segment at its farthest point from the end-point chord until no point
    is farther than ``split_distance_m``. Segments shorter than ``min_points`` are dropped.

    Returns (start, stop) inclusive indices, sorted by start. The split point belongs to both halves.
    All open segments of a level are processed at once: per segment the chord's normal form a x + b y + c = 0
    (unit normal), repeated over its points, gives every point's distance in one vectorised pass.
    """
    x = np.ascontiguousarray(xy_m[:, 0], dtype=np.float64)
    y = np.ascontiguousarray(xy_m[:, 1], dtype=np.float64)
    keep = run_stop - run_start + 1 >= min_points
    start, stop = run_start[keep].astype(np.int64), run_stop[keep].astype(np.int64)
    done_start, done_stop = [], []
    while start.size:
        counts = stop - start + 1
        offsets = np.r_[0, np.cumsum(counts)[:-1]]
        idx = np.arange(counts.sum()) + np.repeat(start - offsets, counts)
        cx, cy = x[stop] - x[start], y[stop] - y[start]
        inv_len = 1.0 / np.maximum(np.hypot(cx, cy), 1e-9)
        a, b = -cy * inv_len, cx * inv_len
        c = -(a * x[start] + b * y[start])
        dist = np.abs(np.repeat(a, counts) * x[idx] + np.repeat(b, counts) * y[idx] + np.repeat(c, counts))
        seg_max = np.maximum.reduceat(dist, offsets)
        at_max = np.flatnonzero(dist == np.repeat(seg_max, counts))
        # the first maximum of each segment: at_max is sorted, segments are contiguous in the flat array
        seg_of = np.searchsorted(offsets, at_max, side="right") - 1
        first = np.r_[True, seg_of[1:] != seg_of[:-1]]
        split_at = idx[at_max[first]]
        final = seg_max <= split_distance_m
        done_start.append(start[final])
        done_stop.append(stop[final])
        s, k, e = start[~final], split_at[~final], stop[~final]
        start, stop = np.r_[s, k], np.r_[k, e]
        keep = stop - start + 1 >= min_points
        start, stop = start[keep], stop[keep]
    start, stop = np.concatenate(done_start or [start]), np.concatenate(done_stop or [stop])
    order = np.argsort(start, kind="stable")
    return start[order], stop[order]


def fit_lines_tls(xy_m: np.ndarray, layer: np.ndarray, start: np.ndarray, stop: np.ndarray, *,
                  end_trim_points: int = 0) -> LineSegments:
    """Total-least-squares line of each segment's points (closed form from segment moment sums).

    ``end_trim_points`` points are left out at each end when the segment is long enough (>= 3 points remain).
    """
    n_all = stop - start + 1
    trim = np.where(n_all - 2 * end_trim_points >= 3, end_trim_points, 0)
    a, b = start + trim, stop - trim
    sums = segment_moment_sums(xy_m, a, b)
    n = (b - a + 1).astype(float)
    mx, my = sums[0] / n, sums[1] / n
    cxx = sums[2] / n - mx * mx
    cxy = sums[3] / n - mx * my
    cyy = sums[4] / n - my * my
    half_diff = 0.5 * (cxx - cyy)
    root = np.hypot(half_diff, cxy)
    mean = 0.5 * (cxx + cyy)
    lam_min = np.maximum(mean - root, 0.0)
    lam_max = mean + root
    dir_rad = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    normal = dir_rad + 0.5 * np.pi
    nx, ny = np.cos(normal), np.sin(normal)
    d = np.column_stack([-ny, nx])
    centroid = np.column_stack([mx, my])
    t0 = np.einsum("ij,ij->i", np.take(xy_m, start, axis=0) - centroid, d)
    t1 = np.einsum("ij,ij->i", np.take(xy_m, stop, axis=0) - centroid, d)
    return LineSegments(start=start, stop=stop, layer=np.asarray(layer)[start], normal_rad=normal,
                        offset_m=nx * mx + ny * my, centroid_xy_m=centroid, n_points=(b - a + 1),
                        residual_var_m2=lam_min, spread_m2=lam_max * n, length_m=np.abs(t1 - t0))


def segment_moment_sums(xy_m: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """(5, K) sums of x, y, xx, xy, yy over points first..last (inclusive) of each segment (ranges may overlap).

    np.add.reduceat over interleaved [first, last + 1] bounds: each even slot is one segment's sum.
    """
    if first.size == 0:
        return np.zeros((5, 0))
    x = np.append(xy_m[:, 0], 0.0)  # a trailing zero keeps last + 1 a valid index
    y = np.append(xy_m[:, 1], 0.0)
    bounds = np.empty(2 * first.size, np.int64)
    bounds[0::2], bounds[1::2] = first, last + 1
    return np.stack([np.add.reduceat(v, bounds)[0::2] for v in (x, y, x * x, x * y, y * y)])


def merge_collinear(lines: LineSegments, *, merge_max_angle_rad: float, merge_max_offset_m: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Merge step: chains of adjacent segments (sharing a split point) that are collinear. Returns (start, stop)."""
    if len(lines) < 2:
        return lines.start, lines.stop
    adjacent = lines.stop[:-1] == lines.start[1:]
    dtheta = np.abs((lines.normal_rad[1:] - lines.normal_rad[:-1] + 0.5 * np.pi) % np.pi - 0.5 * np.pi)
    nx, ny = np.cos(lines.normal_rad), np.sin(lines.normal_rad)
    c = lines.centroid_xy_m
    off_ab = np.abs(nx[:-1] * c[1:, 0] + ny[:-1] * c[1:, 1] - lines.offset_m[:-1])
    off_ba = np.abs(nx[1:] * c[:-1, 0] + ny[1:] * c[:-1, 1] - lines.offset_m[1:])
    merge = adjacent & (dtheta < merge_max_angle_rad) & (np.maximum(off_ab, off_ba) < merge_max_offset_m)
    group = np.r_[0, np.cumsum(~merge)]
    first = np.r_[True, group[1:] != group[:-1]]
    last = np.r_[group[1:] != group[:-1], True]
    return lines.start[first], lines.stop[last]


def extract_lines(xy_m: np.ndarray, layer: np.ndarray, run_starts: np.ndarray, *, split_distance_m: float,
                  min_points: int, merge_max_angle_rad: float, end_trim_points: int) -> LineSegments:
    """IEPF split-and-merge over runs (``run_starts`` from layers.find_run_starts), then TLS refit."""
    n = xy_m.shape[0]
    if n == 0 or run_starts.size == 0:
        return fit_lines_tls(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, np.int64), np.zeros(0, np.int64))
    run_stop = np.r_[run_starts[1:], n] - 1
    start, stop = split_iepf(xy_m, run_starts, run_stop, split_distance_m=split_distance_m, min_points=min_points)
    lines = fit_lines_tls(xy_m, layer, start, stop, end_trim_points=end_trim_points)
    start, stop = merge_collinear(lines, merge_max_angle_rad=merge_max_angle_rad,
                                  merge_max_offset_m=split_distance_m)
    if start.size != len(lines):
        lines = fit_lines_tls(xy_m, layer, start, stop, end_trim_points=end_trim_points)
    return lines


def remove_outlier_lines(lines: LineSegments, *, max_residual_var_m2: float, min_points: int,
                         min_length_m: float) -> np.ndarray:
    """Label each line: LINE, OUTLIER_VARIANCE (paper Figure 5: mean squared residual > threshold, e.g. trees)
    or OUTLIER_SHORT (fewer than ``min_points`` points or shorter than ``min_length_m``)."""
    label = np.full(len(lines), LINE, dtype=np.int8)
    label[lines.residual_var_m2 > max_residual_var_m2] = OUTLIER_VARIANCE
    short = (lines.stop - lines.start + 1 < min_points) | (lines.length_m < min_length_m)
    label[short & (label == LINE)] = OUTLIER_SHORT
    return label
