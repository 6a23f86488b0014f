"""Road-marking raster -> typed vector features (lane lines solid/dashed, stop lines, crosswalks, arrows).

Pure: a binary mask (row 0 = north edge) and its georeference in, ``MarkingFeature`` records (map ENU metres) out.

Method (OpenCV components + principal axes, no learned model):
1. 3 x 3 closing (fills the one-cell holes of a sparsely sampled paint patch), 8-connected components; each
   component's pixel centres give its principal axis, length ``L`` and width ``W`` (extent along / across the
   axis + one cell) and fill ratio (painted area / (L W)).
2. Each component is one of: *piece* of a line (``W <= line_max_width_m`` = 0.35 m), *bar* (up to 0.9 m wide,
   at least 1.2 m long, fill >= 0.6: a crosswalk stripe, a stop line or a double centre line), *arrow*
   (3..7 m long, 0.4..1.3 m wide, fill < 0.6), or noise.
3. Pieces on one straight line (axes within ``chain_angle_deg``, lateral offset <= ``chain_offset_m``, gap
   <= ``chain_gap_m``) chain into one line. A chain whose pieces cover >= ``solid_cover`` of its length with no
   gap over ``dash_gap_m`` is a solid lane line, otherwise dashed; a lone piece shorter than ``min_line_m``
   is noise. Long chains follow curves: the centreline is the mean of the chain's pixels per ``bin_m`` along
   the axis.
4. Three or more parallel bars of similar length (within 2x) side by side (centres within 1.6 m across their
   axes) form a crosswalk (bars within 20 deg, as partly seen stripes skew). Its polygon has sides along the
   stripes' direction (from their long edges, ``marking_crosswalk.stripe_axis``) and across it, on the stripes'
   outer pixel boundaries at sub-pixel precision (``marking_crosswalk.crosswalk_outline``: per scanline the
   outermost cell painted in the mask itself, not by the closing, averaged over the scanlines); a rectangle
   when the stripes are seen whole, a corner moved in to the observed stripe ends where the raster's coverage
   cut them. Any other bar is part of a lane line (a double centre line, or a line the raster drew wide;
   chained with the pieces) when collinear with a piece or another such bar (a dash of a dashed line: axes
   within 6 deg, 0.3 m across, gap <= 6 m), when longer than 15 m (no stop line is), or when at least 5 m long
   with a piece or bar parallel within 6 m; otherwise it is a stop line (its centreline) when at least 2.5 m
   long and at most 0.75 m wide, else noise.
5. Arrows keep their simplified outline (``cv2.approxPolyDP``, 0.1 m).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.marking_crosswalk import crosswalk_outline, stripe_axis

TYPES = ("lane_solid", "lane_dashed", "stop_line", "crosswalk", "arrow")
LINE_TYPES = ("lane_solid", "lane_dashed", "stop_line")
POLYGON_TYPES = ("crosswalk", "arrow")


@dataclass(frozen=True)
class MarkingFeature:
    type: str  # one of TYPES
    xy_m: np.ndarray  # (N, 2) ENU; a polyline for LINE_TYPES, a closed ring (first != last) for POLYGON_TYPES
    width_m: float
    length_m: float

    @property
    def is_polygon(self) -> bool:
        return self.type in POLYGON_TYPES


@dataclass(frozen=True)
class _Comp:
    pts: np.ndarray  # (n, 2) ENU pixel centres
    centre: np.ndarray
    axis: np.ndarray  # unit vector along the component
    s0: float  # extent along the axis relative to the centre
    s1: float
    width_m: float
    fill: float
    ring: np.ndarray  # outline, ENU
    painted: np.ndarray  # (m, 2) ENU centres of the component's cells painted in the mask itself (not by closing)


def _components(mask: np.ndarray, west_m: float, south_m: float, cell_m: float, min_area_m2: float) -> list[_Comp]:
    import cv2

    raw = np.asarray(mask) > 0
    m = cv2.morphologyEx(raw.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    rows = m.shape[0]
    out = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] * cell_m * cell_m < min_area_m2:
            continue
        x0, y0, w, h = (int(stats[k, c]) for c in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH,
                                                    cv2.CC_STAT_HEIGHT))
        sub = (labels[y0:y0 + h, x0:x0 + w] == k)
        r, c = np.nonzero(sub)
        pts = np.column_stack([west_m + (c + x0 + 0.5) * cell_m, south_m + (rows - (r + y0) - 0.5) * cell_m])
        centre = pts.mean(axis=0)
        d = pts - centre
        if len(pts) > 1:
            _, vecs = np.linalg.eigh(d.T @ d)
            axis = vecs[:, 1]
        else:
            axis = np.array([1.0, 0.0])
        if axis[0] < 0 or (axis[0] == 0 and axis[1] < 0):
            axis = -axis
        s = d @ axis
        t = d @ np.array([-axis[1], axis[0]])
        length, width = float(s.max() - s.min() + cell_m), float(t.max() - t.min() + cell_m)
        contours, _ = cv2.findContours(sub.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        ring_px = cv2.approxPolyDP(max(contours, key=len), 0.1 / cell_m, True)[:, 0, :].astype(float)
        ring = np.column_stack([west_m + (ring_px[:, 0] + x0 + 0.5) * cell_m,
                                south_m + (rows - (ring_px[:, 1] + y0) - 0.5) * cell_m])
        painted = raw[y0:y0 + h, x0:x0 + w][r, c]
        out.append(_Comp(pts, centre, axis, float(s.min() - cell_m / 2), float(s.max() + cell_m / 2), width,
                         len(pts) * cell_m * cell_m / (length * width), ring, pts[painted]))
    return out


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def _union_find(n: int, pairs: list[tuple[int, int]]) -> list[list[int]]:
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in pairs:
        parent[find(a)] = find(b)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


def _chain_lines(pieces: list[_Comp], angle_deg: float, offset_m: float, gap_m: float, dash_gap_m: float,
                 solid_cover: float, min_line_m: float, bin_m: float) -> list[MarkingFeature]:
    pairs = []
    for a in range(len(pieces)):
        for b in range(a + 1, len(pieces)):
            pa, pb = pieces[a], pieces[b]
            if _angle_between(pa.axis, pb.axis) > angle_deg:
                continue
            axis = pa.axis if pa.s1 - pa.s0 >= pb.s1 - pb.s0 else pb.axis
            d = pb.centre - pa.centre
            if abs(d @ np.array([-axis[1], axis[0]])) > offset_m:
                continue
            ca, cb = pa.centre @ axis, pb.centre @ axis
            a0, a1 = ca + pa.s0, ca + pa.s1
            b0, b1 = cb + pb.s0, cb + pb.s1
            if max(a0, b0) - min(a1, b1) <= gap_m:
                pairs.append((a, b))
    out = []
    for group in _union_find(len(pieces), pairs):
        pts = np.vstack([pieces[k].pts for k in group])
        centre = pts.mean(axis=0)
        d = pts - centre
        _, vecs = np.linalg.eigh(d.T @ d) if len(pts) > 1 else (None, np.eye(2))
        axis = vecs[:, 1]
        if axis[0] < 0 or (axis[0] == 0 and axis[1] < 0):
            axis = -axis
        normal = np.array([-axis[1], axis[0]])
        intervals = sorted((float(pieces[k].centre @ axis - centre @ axis + pieces[k].s0),
                            float(pieces[k].centre @ axis - centre @ axis + pieces[k].s1)) for k in group)
        s_lo, s_hi = intervals[0][0], max(iv[1] for iv in intervals)
        length = s_hi - s_lo
        covered, reach, max_gap = 0.0, s_lo, 0.0
        for lo, hi in intervals:
            max_gap = max(max_gap, lo - reach)
            covered += max(0.0, hi - max(lo, reach))
            reach = max(reach, hi)
        if length < min_line_m:
            continue
        solid = covered >= solid_cover * length and max_gap <= dash_gap_m
        s = d @ axis
        t = d @ normal
        n_bins = max(1, int(np.ceil(length / bin_m)))
        edges = np.linspace(s_lo, s_hi, n_bins + 1)
        offs = []
        for b in range(n_bins):
            sel = (s >= edges[b]) & (s < edges[b + 1]) if b < n_bins - 1 else (s >= edges[b])
            offs.append(float(np.median(t[sel])) if sel.any() else np.nan)
        offs_arr = np.asarray(offs)
        if np.isnan(offs_arr).all():
            offs_arr[:] = 0.0
        idx = np.arange(n_bins)
        offs_arr = np.interp(idx, idx[~np.isnan(offs_arr)], offs_arr[~np.isnan(offs_arr)])
        if n_bins == 1:
            s_knots, t_knots = np.array([s_lo, s_hi]), np.array([offs_arr[0], offs_arr[0]])
        else:
            mids = 0.5 * (edges[:-1] + edges[1:])
            s_knots = np.concatenate([[s_lo], mids, [s_hi]])
            t_knots = np.concatenate([[offs_arr[0]], offs_arr, [offs_arr[-1]]])
        xy = centre + s_knots[:, None] * axis + t_knots[:, None] * normal
        width = float(np.median([pieces[k].width_m for k in group]))
        out.append(MarkingFeature("lane_solid" if solid else "lane_dashed", xy, width, float(length)))
    return out


def _group_bars(bars: list[_Comp], pieces: list[_Comp], angle_deg: float, pitch_m: float,
                context_m: float, stop_min_m: float, cell_m: float) -> tuple[list[MarkingFeature], list[_Comp]]:
    """Crosswalks and stop lines from the bars; bars that are parallel to a nearby line piece (a short double
    centre line) are returned as line pieces."""
    pairs = []
    for a in range(len(bars)):
        for b in range(a + 1, len(bars)):
            if _angle_between(bars[a].axis, bars[b].axis) > angle_deg:
                continue
            d = bars[b].centre - bars[a].centre
            along = abs(d @ bars[a].axis)
            across = abs(d @ np.array([-bars[a].axis[1], bars[a].axis[0]]))
            la, lb = bars[a].s1 - bars[a].s0, bars[b].s1 - bars[b].s0
            if across <= pitch_m and along <= max(1.0, 0.5 * la) and max(la, lb) <= 2.0 * min(la, lb):
                pairs.append((a, b))
    out, as_pieces = [], []
    groups = _union_find(len(bars), pairs)
    lone = [bars[k] for g in groups if len(g) < 3 for k in g]
    for group in groups:
        if len(group) >= 3:
            axis = stripe_axis([(bars[k].pts, bars[k].axis) for k in group], cell_m)
            box = crosswalk_outline(np.vstack([bars[k].painted for k in group]), axis, cell_m)
            sides = np.linalg.norm(np.diff(box[[0, 1, 2]], axis=0), axis=1)
            out.append(MarkingFeature("crosswalk", box, float(sides.min()), float(sides.max())))
            continue
        for k in group:
            bar = bars[k]
            near = [q for q in pieces + lone if q is not bar
                    and np.min(np.linalg.norm(q.pts - bar.centre, axis=1)) <= context_m]
            length = bar.s1 - bar.s0
            normal = np.array([-bar.axis[1], bar.axis[0]])
            collinear = any(_angle_between(q.axis, bar.axis) <= 6.0 and abs((q.centre - bar.centre) @ normal) <= 0.3
                            for q in pieces + lone if q is not bar
                            and abs((q.centre - bar.centre) @ bar.axis) <= (length + q.s1 - q.s0) / 2 + 6.0)
            if collinear or length > 15.0 or (
                    length >= 5.0 and any(_angle_between(q.axis, bar.axis) <= angle_deg for q in near)):
                as_pieces.append(bar)
                continue
            if length < stop_min_m or bar.width_m > 0.75:
                continue  # a fragment (of a partly seen crosswalk, say): no type
            xy = bar.centre + np.array([bar.s0, bar.s1])[:, None] * bar.axis
            out.append(MarkingFeature("stop_line", xy, bar.width_m, bar.s1 - bar.s0))
    return out, as_pieces


def vectorize_markings(mask: np.ndarray, west_m: float, south_m: float, cell_m: float, *,
                       line_max_width_m: float = 0.35, min_area_m2: float = 0.04, min_line_m: float = 1.5,
                       chain_angle_deg: float = 6.0, chain_offset_m: float = 0.3, chain_gap_m: float = 6.0,
                       dash_gap_m: float = 2.0, solid_cover: float = 0.7, bin_m: float = 5.0) -> list[MarkingFeature]:
    """Typed features of a binary marking raster (row 0 = north edge; south-west corner at (west_m, south_m))."""
    pieces, bars, feats = [], [], []
    for comp in _components(mask, west_m, south_m, cell_m, min_area_m2):
        length = comp.s1 - comp.s0
        if comp.width_m <= line_max_width_m:
            pieces.append(comp)
        elif comp.width_m <= 0.9 and length >= 1.2 and comp.fill >= 0.6:
            bars.append(comp)
        elif 3.0 <= length <= 7.0 and 0.4 <= comp.width_m <= 1.3 and comp.fill < 0.6:
            feats.append(MarkingFeature("arrow", comp.ring, comp.width_m, length))
    bar_feats, more_pieces = _group_bars(bars, pieces, 20.0, 1.6, 6.0, 2.5, cell_m)
    feats += bar_feats
    feats += _chain_lines(pieces + more_pieces, chain_angle_deg, chain_offset_m, chain_gap_m, dash_gap_m,
                          solid_cover, min_line_m, bin_m)
    return feats


def clip_polyline_to_box(xy_m: np.ndarray, e0: float, n0: float, e1: float, n1: float) -> list[np.ndarray]:
    """Parts of a polyline inside [e0, e1) x [n0, n1) (Liang-Barsky per segment), joined where continuous."""
    parts: list[list[np.ndarray]] = []
    for a, b in zip(xy_m[:-1], xy_m[1:]):
        d = b - a
        t0, t1 = 0.0, 1.0
        for p, q in ((-d[0], a[0] - e0), (d[0], e1 - a[0]), (-d[1], a[1] - n0), (d[1], n1 - a[1])):
            if p == 0:
                if q < 0:
                    t0, t1 = 1.0, 0.0
            elif p < 0:
                t0 = max(t0, q / p)
            else:
                t1 = min(t1, q / p)
        if t0 >= t1:
            continue
        pa, pb = a + t0 * d, a + t1 * d
        if parts and np.allclose(parts[-1][-1], pa, atol=1e-9):
            parts[-1].append(pb)
        else:
            parts.append([pa, pb])
    return [np.asarray(p) for p in parts]
