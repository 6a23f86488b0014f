"""Lanelets of the driven lanes: one chain of lanelets per lane a map drive drove, bounded by its painted lines.

Pure (arrays in, records out); ``mapformat.autoware`` writes them as Lanelet2 OSM.

Method:
1. Each drive's trajectory (``T_map_vehicle`` positions, the version's ``trajectories/``), cut where it jumps more
   than ``max_gap_m`` between two poses, is resampled every ``step_m`` along its horizontal arc length; the heading
   at a sample is that of the chord from ``step_m`` before to ``step_m`` after it.
2. A lane is made once: a sample within ``dedup_m`` of a sample already taken (an earlier drive, or this drive
   more than ``segment_m`` earlier) whose heading is within ``dedup_deg`` is dropped. The remaining samples form
   runs; a run shorter than ``min_run_m`` is dropped.
3. The painted lane lines (``lane_solid`` / ``lane_dashed`` vectors, points every 0.25 m) beside each sample are
   found across the heading: on the left the nearest at 0.5 to ``default_width_m`` m, on the right likewise.
4. Each side's paint is the samples that found a line, with gaps of at most ``paint_gap_m`` between two of them
   filled (a dashed line's gaps) and painted stretches shorter than ``min_paint_m`` dropped. A run is cut where the
   paint of either side begins or ends (at its first and last sample that found a line, so no painted boundary
   runs on past the paint, e.g. into an intersection), and each piece into lanelets of about ``segment_m``.
   Each side of a lanelet lies at the median of the lines found on that side when most of its samples are
   painted and at least ``min_line_share`` of them found one (a dashed line is found in about a third of them),
   with the line type of the most found (``solid``, ``dashed``, ``solid_solid`` for a double centre line, i.e. a
   solid line at least 0.55 m wide); else at half of ``default_width_m`` as a ``virtual`` line.
   Consecutive lanelets share their end points (the mean of their two offsets; the painted one's where only one
   is painted), so Lanelet2's routing graph connects them; a boundary point that would step backwards along the
   lane (the inside of a tight turn) is dropped, so no boundary folds over itself.
Heights are the caller's (``height_of``): the road surface of the map under each point.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from stages.common.marking_vectors import MarkingFeature

DOUBLE_LINE_MIN_WIDTH_M = 0.55  # two lines merged in the raster (0.5 m of paint drawn ~0.7 m; a single
# 0.15 m line is drawn 0.3-0.4 m wide)


@dataclass(frozen=True)
class LaneParams:
    step_m: float = 1.0
    segment_m: float = 25.0
    default_width_m: float = 3.5
    min_run_m: float = 10.0
    dedup_m: float = 1.5
    dedup_deg: float = 30.0
    min_line_share: float = 0.2
    max_gap_m: float = 5.0  # a trajectory that jumps further between two poses is two pieces
    paint_gap_m: float = 10.0  # a gap in a side's paint this short is a dashed line's (US dashes: 9.1 m gaps)
    min_paint_m: float = 2.0  # a painted stretch this short is not a line of its own


@dataclass(frozen=True)
class LaneRun:
    """One driven lane: ``left`` / ``right`` boundary points (M, 3) map ENU, and its lanelets as index ranges
    ``cuts[k]..cuts[k+1]`` (inclusive: consecutive lanelets share the point at a cut) into ``left_keep`` /
    ``right_keep`` (the points kept on each side, sorted) with each lanelet's (left, right) line subtype
    (``solid``, ``dashed``, ``solid_solid`` or ``virtual``)."""

    drive: str
    left: np.ndarray
    right: np.ndarray
    left_keep: np.ndarray  # indices into left
    right_keep: np.ndarray
    cuts: np.ndarray  # (L + 1,) sample indices where lanelets start/end
    subtypes: list[tuple[str, str]]

    def lanelet_bounds(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Indices of lanelet ``k``'s left and right boundary points (both along the lane)."""
        a, b = self.cuts[k], self.cuts[k + 1]
        lk, rk = self.left_keep, self.right_keep
        return lk[(lk >= a) & (lk <= b)], rk[(rk >= a) & (rk <= b)]


def resample_path(xyz_m: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) points every ``step_m`` of horizontal arc length and (M,) headings (rad, ENU)."""
    xyz = np.asarray(xyz_m, float)
    if len(xyz) < 2:
        return np.zeros((0, 3)), np.zeros(0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1))])
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    xyz, s = xyz[keep], s[keep]
    if s[-1] < 2 * step_m:
        return np.zeros((0, 3)), np.zeros(0)
    t = np.arange(0.0, s[-1] + 1e-9, step_m)
    pts = np.column_stack([np.interp(t, s, xyz[:, k]) for k in range(3)])
    ahead = np.vstack([pts[1:], pts[-1:]])
    behind = np.vstack([pts[:1], pts[:-1]])
    d = ahead[:, :2] - behind[:, :2]
    return pts, np.arctan2(d[:, 1], d[:, 0])


def _angle_diff(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi)


def lane_line_points(features: list[MarkingFeature], spacing_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing_m`` along the lane lines: (P, 2) ENU and (P,) their subtype."""
    pts, kinds = [], []
    for f in features:
        if f.type not in ("lane_solid", "lane_dashed") or len(f.xy_m) < 2:
            continue
        kind = "dashed" if f.type == "lane_dashed" else (
            "solid_solid" if f.width_m >= DOUBLE_LINE_MIN_WIDTH_M else "solid")
        xy = np.asarray(f.xy_m, float)
        for a, b in zip(xy[:-1], xy[1:]):
            n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing_m)))
            seg = a + (b - a) * (np.arange(n + 1) / n)[:, None]
            pts.append(seg)
            kinds += [kind] * len(seg)
    if not pts:
        return np.zeros((0, 2)), np.zeros(0, dtype=object)
    return np.vstack(pts), np.asarray(kinds, dtype=object)


def _lines_beside(pts: np.ndarray, heading: np.ndarray, line_xy: np.ndarray, line_kind: np.ndarray,
                  max_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per sample, the nearest lane line on the left (offset > 0) and on the right (< 0): offsets (NaN: none) and
    kinds."""
    from scipy.spatial import cKDTree

    m = len(pts)
    off = {+1: np.full(m, np.nan), -1: np.full(m, np.nan)}
    kind = {+1: np.full(m, "", dtype=object), -1: np.full(m, "", dtype=object)}
    if len(line_xy) == 0 or m == 0:
        return off[+1], kind[+1], off[-1], kind[-1]
    tree = cKDTree(line_xy)
    for i, near in enumerate(tree.query_ball_point(pts[:, :2], r=max_m)):
        if not near:
            continue
        q = line_xy[near] - pts[i, :2]
        c, s = np.cos(heading[i]), np.sin(heading[i])
        along, lateral = q @ np.array([c, s]), q @ np.array([-s, c])
        for side in (+1, -1):
            ok = (np.abs(along) <= 0.2) & (side * lateral >= 0.5) & (side * lateral <= max_m)
            if ok.any():
                j = np.flatnonzero(ok)[np.argmin(side * lateral[ok])]
                off[side][i], kind[side][i] = lateral[j], line_kind[near[j]]
    return off[+1], kind[+1], off[-1], kind[-1]


def _forward_only(xy: np.ndarray, heading: np.ndarray, a: int, b: int) -> list[int]:
    """Indices a..b of a boundary whose points keep advancing along the lane (a and b always kept)."""
    keep = [a]
    for i in range(a + 1, b):
        d = xy[i] - xy[keep[-1]]
        if d @ np.array([np.cos(heading[i]), np.sin(heading[i])]) > 0.05 and \
                (xy[b] - xy[i]) @ np.array([np.cos(heading[i]), np.sin(heading[i])]) > 0.05:
            keep.append(i)
    return keep + [b]


def _painted(found: np.ndarray, gap_n: int, min_n: int) -> np.ndarray:
    """Samples on a side's paint: ``found`` with interior gaps of at most ``gap_n`` samples filled, and painted
    stretches of fewer than ``min_n`` samples dropped."""
    painted = found.copy()
    idx = np.flatnonzero(found)
    for a, b in zip(idx[:-1], idx[1:]):
        if 1 < b - a <= gap_n + 1:
            painted[a:b] = True
    edges = np.flatnonzero(np.diff(np.concatenate([[0], painted.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a < min_n:
            painted[a:b] = False
    return painted


def _lanelet_cuts(painted: list[np.ndarray], m: int, p: LaneParams) -> np.ndarray:
    """Sample indices where lanelets start/end: where either side's paint begins or ends, and every
    ``segment_m`` or so between."""
    ends = {0, m - 1}
    for side in painted:
        edges = np.flatnonzero(np.diff(np.concatenate([[0], side.astype(int), [0]])))
        ends.update(edges[::2].tolist())  # the first painted sample of a stretch
        ends.update((edges[1::2] - 1).tolist())  # its last
    cuts = [0]
    for a, b in zip(sorted(ends)[:-1], sorted(ends)[1:]):
        n_cut = max(1, int(round((b - a) * p.step_m / p.segment_m)))
        cuts += np.round(np.linspace(a, b, n_cut + 1)).astype(int)[1:].tolist()
    return np.unique(cuts)


def _run_lanes(drive: str, pts: np.ndarray, heading: np.ndarray, lines: tuple[np.ndarray, np.ndarray],
               p: LaneParams, height_of: Callable[[np.ndarray], np.ndarray]) -> LaneRun:
    m = len(pts)
    lo, lk, ro, rk = _lines_beside(pts, heading, *lines, max_m=p.default_width_m)
    gap_n, min_n = int(p.paint_gap_m / p.step_m), int(np.ceil(p.min_paint_m / p.step_m))
    painted = [_painted(np.isfinite(off), gap_n, min_n) for off in (lo, ro)]
    cuts = _lanelet_cuts(painted, m, p)
    offsets = np.zeros((len(cuts) - 1, 2))
    subtypes = []
    for k in range(len(cuts) - 1):
        sl = slice(cuts[k], cuts[k + 1] + 1)
        kinds = []
        for col, (off, kind, sign) in enumerate(((lo, lk, +1), (ro, rk, -1))):
            found = np.isfinite(off[sl])
            if painted[col][sl].mean() > 0.5 and found.any() and found.mean() >= p.min_line_share:
                offsets[k, col] = float(np.median(off[sl][found]))
                names, counts = np.unique(kind[sl][found].astype(str), return_counts=True)
                kinds.append(str(names[np.argmax(counts)]))
            else:
                offsets[k, col] = sign * p.default_width_m / 2
                kinds.append("virtual")
        subtypes.append((kinds[0], kinds[1]))
    per_sample = np.zeros((m, 2))
    for k in range(len(cuts) - 1):
        per_sample[cuts[k]:cuts[k + 1] + 1] = offsets[k]
    for k in range(1, len(cuts) - 1):  # a shared end point: between the two lanelets' offsets
        for col in (0, 1):  # on the paint where only one of the two is painted (where the paint ends)
            virtual = [subtypes[k - 1][col] == "virtual", subtypes[k][col] == "virtual"]
            per_sample[cuts[k], col] = (offsets[k - 1, col] if virtual[1] and not virtual[0] else
                                        offsets[k, col] if virtual[0] and not virtual[1] else
                                        offsets[k - 1:k + 1, col].mean())
    normal = np.column_stack([-np.sin(heading), np.cos(heading)])
    sides = []
    for col in (0, 1):
        xy = pts[:, :2] + normal * per_sample[:, col:col + 1]
        z = height_of(xy)
        z = np.where(np.isfinite(z), z, pts[:, 2])
        keep = sorted({i for k in range(len(cuts) - 1) for i in _forward_only(xy, heading, cuts[k], cuts[k + 1])})
        sides.append((np.column_stack([xy, z]), np.asarray(keep, int)))
    return LaneRun(drive, sides[0][0], sides[1][0], sides[0][1], sides[1][1], cuts, subtypes)


def driven_lanes(paths: dict[str, np.ndarray], features: list[MarkingFeature],
                 height_of: Callable[[np.ndarray], np.ndarray], params: LaneParams = LaneParams()) -> list[LaneRun]:
    """The driven lanes of ``paths`` (drive -> (N, 3) vehicle positions, map ENU) as ``LaneRun``s (method above)."""
    from scipy.spatial import cKDTree

    p = params
    lines = lane_line_points(features)
    taken_xy, taken_h = np.zeros((0, 2)), np.zeros(0)
    runs = []
    pieces = []
    for drive in sorted(paths):
        xyz = np.asarray(paths[drive], float).reshape(-1, 3)
        jumps = np.flatnonzero(np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1) > p.max_gap_m) + 1
        pieces += [(drive, piece) for piece in np.split(xyz, jumps)]
    for drive, piece in pieces:
        pts, heading = resample_path(piece, p.step_m)
        if not len(pts):
            continue
        free = np.ones(len(pts), bool)
        if len(taken_xy):
            for i, near in enumerate(cKDTree(taken_xy).query_ball_point(pts[:, :2], r=p.dedup_m)):
                if near and (_angle_diff(taken_h[near], heading[i]) < np.radians(p.dedup_deg)).any():
                    free[i] = False
        lag = int(np.ceil(p.segment_m / p.step_m))
        for i, j in sorted(cKDTree(pts[:, :2]).query_pairs(r=p.dedup_m)):  # this drive's own second pass
            if j - i > lag and free[i] and _angle_diff(heading[i], heading[j]) < np.radians(p.dedup_deg):
                free[j] = False
        edges = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if (b - a - 1) * p.step_m >= p.min_run_m:
                runs.append(_run_lanes(drive, pts[a:b], heading[a:b], lines, p, height_of))
        taken_xy = np.vstack([taken_xy, pts[free, :2]])
        taken_h = np.concatenate([taken_h, heading[free]])
    return runs
