"""A crosswalk's outline from its stripes' pixels (pure; used by ``marking_vectors``).

Sub-pixel sides: per scanline (pixels binned in cells across a side) the outermost cell painted in the mask
itself is moved half a cell outwards; the mean of these ends over the scanlines is unbiased when a cell is
painted with the probability of its paint cover (one lidar point per cell). A crosswalk the raster's coverage
cut (its stripes end at the cut, not at the paint's end) is not a rectangle: the stripes' direction is taken
from their long edges, which a cut does not tilt, and a corner whose stripe ends fall short of the side's common
end is placed at the observed ends there rather than extrapolated past the cells seen as paint. On synthetic
crosswalks cut at random angles (tests/stages/common/test_marking_crosswalk.py; docs/markings.md) every corner
lies on the paint (at most 4 cm outside it) and most on the seen part; a cut shaving under about 0.2 m off a
corner is below what the scanlines tell from a ragged end, and leaves that corner up to 0.15 m past the cut (on
the unseen paint).
"""
from __future__ import annotations

import numpy as np


def stripe_axis(stripes: list[tuple[np.ndarray, np.ndarray]], cell_m: float) -> np.ndarray:
    """Unit direction of a crosswalk's stripes, each given as (pixel centres (n, 2), principal axis).

    Start: the principal axes (signs aligned, weighted by pixel counts). A stripe a coverage cut ends obliquely
    is a trapezoid whose principal axis turns by 1-2 deg, which put the far corners of a partly seen crosswalk
    6 cm off the paint; so the direction is turned (twice) by the slope of the stripes' midlines (the middle
    between a stripe's two long edges, per cell along it) over the stretches where a stripe has its full width
    (within a cell of its median), which a cut across its end does not tilt."""
    ref = stripes[0][1]
    u = np.sum([len(p) * (a if a @ ref >= 0 else -a) for p, a in stripes], axis=0)
    u = u / np.linalg.norm(u)
    for _ in range(2):
        v = np.array([-u[1], u[0]])
        sxx = sxy = 0.0
        for pts, _axis in stripes:
            s, t = pts @ u, pts @ v
            keys, inv = np.unique(np.floor(s / cell_m).astype(np.int64), return_inverse=True)
            lo, hi = np.full(len(keys), np.inf), np.full(len(keys), -np.inf)
            np.minimum.at(lo, inv, t)
            np.maximum.at(hi, inv, t)
            full = hi - lo >= np.median(hi - lo) - cell_m * 1.01
            if full.sum() < 3:
                continue
            x, mid = keys[full] * cell_m, (lo[full] + hi[full]) / 2
            x, mid = x - x.mean(), mid - mid.mean()
            sxx, sxy = sxx + float(x @ x), sxy + float(x @ mid)
        if sxx <= 0:
            break
        u = u + (sxy / sxx) * v
        u = u / np.linalg.norm(u)
    return u


def scanlines(along: np.ndarray, across: np.ndarray, cell_m: float) -> dict[str, np.ndarray]:
    """Pixels binned by ``across`` in cells: per scanline its centre across (``x``), its pixel boundaries along
    (``lo``, ``hi``: the extreme pixel centres moved half a cell outwards) and its pixel count (``n``)."""
    bins = np.floor(across / cell_m).astype(np.int64)
    keys, inv, n = np.unique(bins, return_inverse=True, return_counts=True)
    lo, hi = np.full(len(keys), np.inf), np.full(len(keys), -np.inf)
    np.minimum.at(lo, inv, along)
    np.maximum.at(hi, inv, along)
    return {"x": (keys + 0.5) * cell_m, "lo": lo - cell_m / 2, "hi": hi + cell_m / 2, "n": n}


def outer_cluster(ends: np.ndarray, cell_m: float, upper: bool) -> float:
    """A side's common position from its scanline ends: the outermost cluster of ends (split where they jump by
    over 2 cells) holding at least max(3, 10 %) of the scanlines, averaged over its ends within a cell of its
    median (a ragged end, the sparse scanline along a tilted stripe edge are left out). Whole stripes make one
    cluster; a coverage cut that left a short piece of an outer stripe keeps that piece's edge as the side."""
    ys = np.sort(ends)[::-1] if upper else np.sort(ends)
    need = max(3, int(np.ceil(0.1 * len(ys))))
    parts = np.split(ys, np.flatnonzero(np.abs(np.diff(ys)) > 2 * cell_m) + 1)
    part = next((p for p in parts if len(p) >= need), ys)
    return float(np.mean(part[np.abs(part - np.median(part)) <= cell_m + 1e-9]))


def corner_end(lines: dict[str, np.ndarray], upper: bool, x_edge: float, flat_m: float, opposite_m: float,
               cell_m: float) -> float:
    """Where the stripes end at one corner of a side whose common end is ``flat_m``: ``flat_m`` unless a coverage
    cut shortened them there, then the observed ends at the corner (never past ``flat_m``).

    Looked at: the scanlines anchored at the opposite side (their other end within 1.5 cells of ``opposite_m``)
    and dense (at least 3 pixels, painted over at least 70 % of their span): a sparse scanline along a tilted
    stripe edge is neither, a cut one is both. Two estimates of the ends at ``x_edge``, each a Theil-Sen line
    (robust to a ragged end) of the ends: (a) of the scanlines within 0.45 m of the one nearest ``x_edge`` (the
    outer stripe), taken when two of them fall over 1.5 cells short of ``flat_m`` (one end scatters by about a
    cell); (b) of the stripes' median ends (runs of such scanlines, at least 3), taken when it slopes by over 1.5
    cells across the side (a cut oblique to the whole side; the ends within a stripe step with the pixel grid,
    which a line through all scanlines would take for a slope). The innermost of those taken."""
    from scipy.stats import theilslopes

    far, near_end = (lines["lo"], lines["hi"]) if upper else (lines["hi"], lines["lo"])
    span = lines["hi"] - lines["lo"]
    ok = (np.abs(far - opposite_m) <= 1.5 * cell_m) & (lines["n"] >= 3) & (lines["n"] * cell_m >= 0.7 * span)
    if ok.sum() < 3:
        return flat_m
    x, y = lines["x"][ok], near_end[ok]
    sign = 1.0 if upper else -1.0
    found = [flat_m]
    nearest = x[np.argmin(np.abs(x - x_edge))]
    keep = np.abs(x - nearest) <= 0.45 + 1e-9
    if abs(nearest - x_edge) <= 0.3 and keep.sum() >= 3 and (sign * (flat_m - y[keep]) > 1.5 * cell_m).sum() >= 2:
        slope, intercept, _, _ = theilslopes(y[keep], x[keep])
        found.append(intercept + slope * x_edge)
    runs = np.split(np.arange(len(x)), np.flatnonzero(np.diff(x) > 2.5 * cell_m) + 1)  # stripes
    if len(runs) >= 3:
        xm, ym = np.array([np.median(x[r]) for r in runs]), np.array([np.median(y[r]) for r in runs])
        slope, intercept, _, _ = theilslopes(ym, xm)
        if abs(slope) * (xm.max() - xm.min()) > 1.5 * cell_m:
            found.append(intercept + slope * x_edge)
    return float(min(found) if upper else max(found))


def _outer_stripe(across: np.ndarray, cell_m: float, upper: bool) -> np.ndarray:
    """Pixels of the outermost stripe on one side (mask): the run of occupied scanlines from that side up to the
    first gap of two or more empty ones (the gap to the next stripe)."""
    bins = np.floor(across / cell_m).astype(np.int64)
    occupied = np.unique(bins)[::-1] if upper else np.unique(bins)
    gaps = np.flatnonzero(np.abs(np.diff(occupied)) > 2)
    return np.isin(bins, occupied[:gaps[0] + 1] if len(gaps) else occupied)


def crosswalk_outline(pts_m: np.ndarray, axis: np.ndarray, cell_m: float) -> np.ndarray:
    """Outline (4, 2) of a crosswalk from its stripes' painted pixel centres (ENU) and the stripes' direction:
    sides across at the outer long edges of the first and last stripe, sides along at the stripes' ends (each
    ``outer_cluster``). A rectangle when every stripe is seen whole. Where a coverage cut shortened the stripes
    at a corner, or narrowed the outer stripe there (``corner_end`` along the stripes' ends, along the outer
    stripe's long edge), the corner moves in to the observed paint: the side follows the cut as a chord of the
    seen ends."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.array([-u[1], u[0]])
    c = pts_m.mean(axis=0)
    s, t = (pts_m - c) @ u, (pts_m - c) @ v
    across = scanlines(t, s, cell_m)
    t_flat = {up: outer_cluster(across["hi" if up else "lo"], cell_m, up) for up in (False, True)}
    along = scanlines(s, t, cell_m)
    s_flat = {up: outer_cluster(along["hi" if up else "lo"], cell_m, up) for up in (False, True)}
    s_end = {(us, ut): corner_end(along, us, t_flat[ut], s_flat[us], s_flat[not us], cell_m)
             for us in (False, True) for ut in (False, True)}
    t_end = {}
    for ut in (False, True):
        sel = _outer_stripe(t, cell_m, ut)
        stripe = scanlines(t[sel], s[sel], cell_m)
        inner = outer_cluster(stripe["lo" if ut else "hi"], cell_m, not ut)
        for us in (False, True):
            t_end[us, ut] = corner_end(stripe, ut, s_flat[us], t_flat[ut], inner, cell_m)
    return np.array([c + s_end[k] * u + t_end[k] * v for k in ((False, False), (True, False), (True, True),
                                                                 (False, True))])
